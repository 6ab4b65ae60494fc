"""Retrace guards: the predict path and both training steps compile once per shape.

Each guard counts how often the traced Python body runs (a side effect that happens
only while jax traces), so a change that makes a static argument unhashable-by-value,
passes a Python scalar as static or rebuilds a jitted function per call shows up as
extra traces.
"""

import dataclasses

import numpy as np
import pytest

from configs import diffusion as diffusion_config
from configs import tokenizer as tokenizer_config
from cvmdx_jax.benchmarks import random_models
from cvmdx_jax.config.runs import DiffusionRunConfig, TokenizerRunConfig
from cvmdx_jax.config.sampling import SamplingConfig
from cvmdx_jax.inference import predictor as predict
from tests.train import toy
from tests.train.toy_job import task


def _counting(fn, counter: list):
  def wrapped(*args, **kwargs):
    counter.append(1)
    return fn(*args, **kwargs)

  return wrapped


def _random_predictor(chunk_size: int | None) -> predict.Predictor:
  """A Predictor of untrained :tiny models (the weights do not matter for tracing)."""
  tok_cfg = TokenizerRunConfig.from_config(tokenizer_config.get_config("tiny")).model
  config = DiffusionRunConfig.from_config(diffusion_config.get_config("tiny"))
  config = config.with_tokens(tok_cfg.quantizer.codebook_size)
  sampling = SamplingConfig(num_samples=3, steps=2)
  return random_models.random_predictor(tok_cfg, config, sampling, chunk_size)


_scenarios = random_models.random_scenarios


def test_predict_path_compiles_once_per_chunk_shape(monkeypatch):
  traces = []
  monkeypatch.setattr(predict, "predict_batch", _counting(predict.predict_batch, traces))
  predict._predict.clear_cache()
  predictor = _random_predictor(chunk_size=4)
  scenarios = _scenarios(6)  # chunks of 4 and 2 (padded to 4)
  first = predictor(scenarios, seed=0)
  predictor(scenarios, seed=1)
  # a predictor rebuilt from the same runs (equal static fields) reuses the compilation
  dataclasses.replace(predictor, sampling=SamplingConfig(num_samples=3, steps=2))(scenarios)
  assert len(traces) == 1
  assert first.prediction.trajectories.shape == (6, 3, 125, 2)
  dataclasses.replace(predictor, chunk_size=2)(scenarios)  # another chunk shape: one more
  assert len(traces) == 2


def test_default_chunk_bounds_the_samples_of_a_call_not_the_scenarios(monkeypatch):
  assert [predict.default_chunk(n) for n in (1, 9, 16, 64, 4096, 10_000)] == [
      256,
      256,
      144,
      36,
      1,
      1,
  ]
  monkeypatch.setattr(predict, "SAMPLES_PER_CALL", 6)  # N = 3: 2 scenarios a call
  predictor = _random_predictor(chunk_size=None)
  assert predictor.scenarios_per_call == 2
  scenarios = _scenarios(5)
  auto = predictor(scenarios, seed=0).prediction.trajectories
  fixed = dataclasses.replace(predictor, chunk_size=2)(scenarios, seed=0).prediction.trajectories
  assert auto.shape == (5, 3, 125, 2)
  np.testing.assert_array_equal(auto, fixed)  # the same chunk shape: the same kernels


@pytest.mark.parametrize("name", [pytest.param("diffusion", marks=pytest.mark.slow), "tokenizer"])
def test_training_step_compiles_once(tmp_path, name):
  init_fn, step_fn, data = task(name, 12)  # batch 8: one full and one padded batch an epoch
  traces = []
  toy.train(
      workdir=tmp_path,
      init_fn=init_fn,
      step_fn=_counting(step_fn, traces),
      data=data,
      batch_size=8,
      num_epochs=2,
      seed=0,
      fingerprint={"task": name},
  )
  assert len(traces) == 1
