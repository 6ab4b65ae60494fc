"""Run-directory format and config plumbing: the prediction path stands without the
trainers, the loop without the prediction path; config sections become the typed configs,
each field checked by the dataclass that holds it."""

import dataclasses
import subprocess
import sys
from pathlib import Path

import ml_collections
import pytest

from configs import diffusion as diffusion_config
from configs import tokenizer as tokenizer_config
from cvmdx_jax.config.fields import ConfigFieldError, to_dataclass
from cvmdx_jax.config.models import UNetConfig
from cvmdx_jax.config.runs import DiffusionRunConfig, DistillRunConfig, TokenizerRunConfig
from cvmdx_jax.config.sampling import GuidanceConfig, HypothesisConfig, SamplingConfig
from cvmdx_jax.runs import fingerprints
from tests.subprocess_env import environ

REPO = Path(__file__).resolve().parents[2]


def _imported(modules: str, prefix: str) -> list[str]:
  code = (
      f"import sys, {modules}; "
      f"print(sorted(m for m in sys.modules if m.startswith({prefix!r})))"
  )
  proc = subprocess.run(
      [sys.executable, "-c", code],
      cwd=REPO,
      capture_output=True,
      text=True,
      timeout=300,
      env=environ(),
  )
  assert proc.returncode == 0, proc.stderr[-2000:]
  return eval(proc.stdout.strip().splitlines()[-1])  # a printed list of names


def test_prediction_path_does_not_import_the_trainers():
  assert _imported("cvmdx_jax.inference.predictor, cvmdx_jax.runs.loaders", "cvmdx_jax.train") == []


def test_the_training_loop_does_not_import_the_inference_path():
  assert _imported("cvmdx_jax.train.loop", "cvmdx_jax.inference") == []
  assert "cvmdx_jax.runs.loaders" not in _imported("cvmdx_jax.train.loop", "cvmdx_jax.runs")


def test_the_trainers_and_the_run_configs_do_not_load_the_sampler():
  """The typed configs live below the models (cvmdx_jax.config): building a run config
  imports no inference code, and a trainer at most the bundles (a distillation's teacher),
  never the sampler or the predictor."""
  assert _imported("cvmdx_jax.config.runs", "cvmdx_jax.inference") == []
  trainers = (
      "cvmdx_jax.train.tokenizer, cvmdx_jax.train.diffusion, cvmdx_jax.train.distill, "
      "cvmdx_jax.train.baseline"
  )
  assert _imported(trainers, "cvmdx_jax.inference") in (
      [],
      ["cvmdx_jax.inference", "cvmdx_jax.inference.bundles"],
  )


def test_to_dataclass_builds_nested_sections_and_names_unknown_keys():
  section = ml_collections.ConfigDict(
      {"steps": 4, "guidance": {"w_min": 0.3}, "hypotheses": {"c_max": 2}}
  )
  out = to_dataclass(SamplingConfig, section, clip_x0=0.5)
  assert out.steps == 4 and out.clip_x0 == 0.5
  assert out.guidance == GuidanceConfig(w_min=0.3) and out.hypotheses.c_max == 2
  assert out.num_samples == 9  # left out: the dataclass default
  hash(out)  # usable as a static jit argument
  with pytest.raises(ValueError, match=r"UNetConfig: unknown field\(s\) \['channel_mul'\]"):
    to_dataclass(UNetConfig, {"channel_mul": [1, 2]})


def test_run_configs_become_the_typed_configs():
  demo = DiffusionRunConfig.from_config(diffusion_config.get_config("demo"))
  assert demo.diffusion.control_scale == (4.0, 0.1) and demo.sampling.clip_x0 == 1.0
  assert demo.sampling.guidance.w_max_base == 0.0 and demo.sampling.intent_prior == (2, 1, 1)
  assert (demo.sampling.sampler, demo.sampling.steps) == ("dpmpp2m", 3)  # chosen on val
  assert demo.diffusion.class_weights == (1.0, 1.0, 1.0)  # chosen on val
  assert demo.model.cond_hidden == (256, 256)  # chosen on val
  assert demo.train.batch_size == 128  # chosen on val
  assert not demo.diffusion.weighted_classes
  # chosen on val (docs/log, "Hypotheses for coverage"); the paper keeps BIC over 9
  assert (demo.sampling.num_samples, demo.sampling.hypotheses.method) == (64, "kmeans")
  assert demo.sampling.hypotheses.endpoint_weight == 0.5
  # p(c) temperature chosen on val (docs/log/2026-12-06-prob-temperature.md); paper: shares
  assert demo.sampling.hypotheses.prob_temperature == 0.6
  for preset in ("paper", "reference"):
    sampling = DiffusionRunConfig.from_config(diffusion_config.get_config(preset)).sampling
    assert (sampling.num_samples, sampling.hypotheses) == (9, HypothesisConfig())
  paper = DiffusionRunConfig.from_config(diffusion_config.get_config("paper"))
  assert paper.diffusion.class_weights == (1.0, 1.0, 1.0) and not paper.diffusion.weighted_classes
  assert demo.model.channel_mult == (1, 2, 2, 2) and demo.model.attention_levels == (3,)
  assert demo.model.num_tokens == 0 and demo.with_tokens(60).model.null_token == 60
  assert demo.model.cond_dim > 0 and paper.model.cond_dim == 0  # ego_film_residual vs token
  assert paper.model.cond_hidden == ()
  assert demo.diffusion.intent_conditioning and demo.model.num_intents == 3  # chosen on val
  assert not paper.diffusion.intent_conditioning and paper.model.num_intents == 0
  unclipped = diffusion_config.get_config("demo")
  unclipped.sampling.clip_x0 = 0.0  # 0 = no clipping
  assert DiffusionRunConfig.from_config(unclipped).sampling.clip_x0 is None
  tok = TokenizerRunConfig.from_config(tokenizer_config.get_config("tiny,quantizer=vq,q=5"))
  assert tok.model.quantizer.kind == "vq" and tok.model.quantizer.codebook_size == 5
  assert tok.model.quantizer.latent_dim == tok.model.encoder.latent_dim == 4
  assert tok.model.encoder.channels == (8, 8) and tok.model.ego_weight == 30.0
  hash(demo), hash(tok)


def _with(config, field: str, value):
  """`config` with its dotted `field` set to `value`."""
  *path, name = field.split(".")
  section = config
  for part in path:
    section = section[part]
  section[name] = value
  return config


@pytest.mark.parametrize(
    "field, value, problem",
    [
        ("train.num_epochs", -3, "must be > 0"),
        ("diffusion.cond_drop_prob", 1.0, "must be in [0, 1)"),
        ("diffusion.class_weights", (1.0, 0.0, 1.0), "must be > 0"),
        ("diffusion.class_weights", (1.0, 2.0), "need 3 positive finite weights"),
        ("model.dropout", float("nan"), "must be finite"),
        ("sampling.guidance.t_c", 0.0, "must be > 0"),
        ("sampling.hypotheses.endpoint_weight", 1.5, "must be in [0, 1]"),
        ("sampling.hypotheses.prob_temperature", 0.0, "must be > 0"),
        ("seed", 2**32, "must be in [0, 2**32)"),
    ],
)
def test_a_diffusion_field_out_of_range_is_named_by_its_dotted_path(field, value, problem):
  with pytest.raises(ConfigFieldError) as error:
    DiffusionRunConfig.from_config(_with(diffusion_config.get_config("tiny"), field, value))
  assert error.value.field == field and problem in error.value.problem


@pytest.mark.parametrize("value", [1, 0, 2.5])
def test_distill_teacher_substeps_must_be_an_integer_of_at_least_two(value):
  with pytest.raises(ConfigFieldError) as error:
    DistillRunConfig(teacher_substeps=value)
  assert error.value.field == "teacher_substeps" and "integer >= 2" in error.value.problem
  assert DistillRunConfig(teacher_substeps=5).teacher_substeps == 5


@pytest.mark.parametrize(
    "field, value",
    [
        ("quantizer.usage_decay", 1.5),
        ("model.encoder.latent_dim", 0),
        ("uncertainty.ridge", -1.0),
        ("encode_batch", 0),
        ("train.grad_clip", -1.0),
    ],
)
def test_a_tokenizer_field_out_of_range_is_named_by_its_dotted_path(field, value):
  with pytest.raises(ConfigFieldError) as error:
    TokenizerRunConfig.from_config(_with(tokenizer_config.get_config("tiny"), field, value))
  assert error.value.field == field


def test_the_diffusion_fingerprint_holds_the_whole_unet_config():
  """Every U-Net field is part of the fingerprint (no field left out for older runs): two
  runs that differ in the conditioning MLP's widths are not one run."""
  config = DiffusionRunConfig.from_config(diffusion_config.get_config("demo")).with_tokens(8)
  meta = {"checkpoint": {"fingerprint": {}, "step": 1, "params_id": "x"}}
  fingerprint = fingerprints.diffusion(config, "data", meta)
  assert fingerprint["model"] == dataclasses.asdict(config.model)
  assert fingerprint["intent_conditioning"] is True
  wide = dataclasses.replace(
      config, model=dataclasses.replace(config.model, cond_hidden=(256, 512))
  )
  assert fingerprints.diffusion(wide, "data", meta) != fingerprint
  assert fingerprints.diffusion(wide, "data", meta)["model"]["cond_hidden"] == (256, 512)
