"""The predictor refuses hostile settings and inputs with a `UserError` naming them: a
chunk size that is not a positive whole number, scenarios whose xi is text or whose v0 is
complex (they used to skip the finiteness check or be truncated to their real part), a
progressive student sampled at other steps than its own."""

import dataclasses

import numpy as np
import pytest

from cvmdx_jax.config.sampling import SamplingConfig
from cvmdx_jax.data import dataset
from cvmdx_jax.errors import UserError
from cvmdx_jax.inference.predictor import Predictor
from cvmdx_jax.inference.predictor_inputs import check_student_steps


@pytest.fixture(scope="module")
def loaded(tiny_runs):
  scenarios = dataset.load_split(tiny_runs / "data", "test").take(np.arange(2))
  return Predictor.load(tiny_runs / "tokenizer", tiny_runs / "diffusion"), scenarios


@pytest.mark.slow  # the session's tiny runs
@pytest.mark.parametrize("chunk_size", [0, -1, 2.5, "8", True])
def test_chunk_size_must_be_a_positive_whole_number(loaded, chunk_size):
  predictor, _ = loaded
  with pytest.raises(UserError, match=r"^chunk_size="):
    dataclasses.replace(predictor, chunk_size=chunk_size)


@pytest.mark.slow  # the session's tiny runs
@pytest.mark.parametrize(
    "field, make",
    [
        ("xi", lambda s: s.xi.astype(str)),
        ("xi", lambda s: s.xi.astype(object)),
        ("v0", lambda s: s.v0 + 1j),
    ],
)
def test_inputs_that_are_not_real_numbers_are_refused(loaded, field, make):
  predictor, scenarios = loaded
  bad = dataclasses.replace(scenarios, **{field: make(scenarios)})
  with pytest.raises(UserError, match=f"field '{field}' has dtype"):
    predictor(bad)


@pytest.mark.parametrize("stage", ["progressive", "guided_progressive"])
def test_a_progressive_student_samples_only_at_its_own_steps(stage):
  fingerprint = {"distill": {"stage": stage, "steps": 2}}
  check_student_steps(SamplingConfig(sampler="distilled", steps=2), fingerprint)
  for sampling in (
      SamplingConfig(sampler="distilled", steps=4),
      SamplingConfig(sampler="ddim", steps=2),
  ):
    with pytest.raises(UserError, match=f"distilled \\({stage}\\) to sample in 2 steps"):
      check_student_steps(sampling, fingerprint)


def test_other_denoisers_sample_at_any_steps():
  for fingerprint in ({}, {"distill": {"stage": "guidance", "steps": 2}}):
    check_student_steps(SamplingConfig(sampler="ddim", steps=7), fingerprint)
