"""Run-directory format and config plumbing: the prediction path stands without the
trainers; config sections become the model / sampling dataclasses."""

import os
import subprocess
import sys
from pathlib import Path

import ml_collections
import pytest

from configs import diffusion as diffusion_config
from configs import tokenizer as tokenizer_config
from cvmdx_jax import runs
from cvmdx_jax.config_dataclass import to_dataclass
from cvmdx_jax.diffusion import GuidanceConfig
from cvmdx_jax.inference import SamplingConfig
from cvmdx_jax.models import unet1d
from cvmdx_jax.multimodal import HypothesisConfig
from cvmdx_jax.train import tokenizer as tokenizer_train

REPO = Path(__file__).resolve().parents[1]


def test_prediction_path_does_not_import_the_trainers():
  code = ("import sys, cvmdx_jax.predict, cvmdx_jax.runs, cvmdx_jax.inference; "
          "print(sorted(m for m in sys.modules if m.startswith('cvmdx_jax.train')))")
  proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True,
                        text=True, timeout=300, env=dict(os.environ, PYTHONPATH=str(REPO)))
  assert proc.returncode == 0, proc.stderr[-2000:]
  assert proc.stdout.strip().splitlines()[-1] == "[]"


def test_to_dataclass_builds_nested_sections_and_names_unknown_keys():
  section = ml_collections.ConfigDict({"steps": 4, "guidance": {"w_min": 0.3},
                                       "hypotheses": {"c_max": 2}})
  out = to_dataclass(SamplingConfig, section, control_scale=[4.0, 0.1])
  assert out.steps == 4 and out.control_scale == (4.0, 0.1)  # list -> tuple
  assert out.guidance == GuidanceConfig(w_min=0.3) and out.hypotheses.c_max == 2
  assert out.num_samples == 9  # left out: the dataclass default
  hash(out)  # usable as a static jit argument
  with pytest.raises(ValueError, match=r"UNetConfig: unknown field\(s\) \['channel_mul'\]"):
    to_dataclass(unet1d.UNetConfig, {"channel_mul": [1, 2]})


def test_run_configs_become_the_model_and_sampling_settings():
  demo = diffusion_config.get_config("demo")
  sampling = runs.sampling_config(demo)
  assert sampling.control_scale == (4.0, 0.1) and sampling.clip_x0 == 1.0
  assert sampling.guidance.w_max_base == 0.5
  assert (sampling.sampler, sampling.steps) == ("dpmpp2m", 3)  # chosen on val (BUILD_NOTES)
  assert tuple(demo.diffusion.class_weights) == (3.0, 1.0, 1.0)  # chosen on val
  # chosen on val (BUILD_NOTES, "Hypotheses for coverage"); the paper keeps BIC over 9
  assert (sampling.num_samples, sampling.hypotheses.method) == (36, "kmeans")
  assert sampling.hypotheses.endpoint_weight == 0.5
  for preset in ("paper", "reference"):
    paper = runs.sampling_config(diffusion_config.get_config(preset))
    assert (paper.num_samples, paper.hypotheses) == (9, HypothesisConfig())
  assert tuple(diffusion_config.get_config("paper").diffusion.class_weights) == (1.0, 1.0, 1.0)
  demo.sampling.clip_x0 = 0.0  # 0 = no clipping
  assert runs.sampling_config(demo).clip_x0 is None
  unet = to_dataclass(unet1d.UNetConfig, demo.model, num_tokens=60)
  assert unet.channel_mult == (1, 2, 2, 2) and unet.attention_levels == (3,)
  assert unet.null_token == 60
  tok = tokenizer_train.model_config(tokenizer_config.get_config("tiny,quantizer=vq,q=5"))
  assert tok.quantizer.kind == "vq" and tok.quantizer.codebook_size == 5
  assert tok.quantizer.latent_dim == tok.encoder.latent_dim == 4
  assert tok.encoder.channels == (8, 8) and tok.ego_weight == 30.0
