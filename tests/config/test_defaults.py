"""One source of defaults: the presets of configs/*.py against the run-config dataclasses.

The dataclasses' defaults are the base presets, field for field, except the choices listed
here (each a deliberate difference, named where it is made); `:paper` is the paper's
training and sampling setup (shared/paper, "Implementation details": B2 = 256,
lr2 = 2.0e-4, E2 = 2000, DDIM S = 10, t_c = 50, w_max,base = 1, w_min = 0.1).
"""

import dataclasses

import pytest

from configs import baseline, diffusion, distill, tokenizer
from cvmdx_jax.config.runs import (
    BaselineRunConfig,
    DiffusionRunConfig,
    DistillRunConfig,
    TokenizerRunConfig,
)

# field -> the base preset's value, where it differs from the dataclass default on purpose
CHOICES = {
    # the paper samples with DDIM-10 (the dataclass default); the base preset with
    # DPM-Solver++(2M) in 3 steps (docs/results.md, "Samplers")
    "diffusion": {"sampling.sampler": "dpmpp2m", "sampling.steps": 3},
    # the model defaults are CVQ's and the paper's; the preset's revival and ego weight
    # were chosen on val (configs/tokenizer.py)
    "tokenizer": {"model.quantizer.revive_strength": 0.1, "model.ego_weight": 30.0},
    "baseline": {},
    "distill": {},
}
RUNS = {
    "diffusion": (diffusion, DiffusionRunConfig),
    "tokenizer": (tokenizer, TokenizerRunConfig),
    "baseline": (baseline, BaselineRunConfig),
    "distill": (distill, DistillRunConfig),
}


def _flat(tree: dict, prefix: str = "") -> dict:
  out = {}
  for key, value in tree.items():
    if isinstance(value, dict):
      out.update(_flat(value, f"{prefix}{key}."))
    else:
      out[f"{prefix}{key}"] = value
  return out


@pytest.mark.parametrize("name", sorted(RUNS))
def test_the_base_preset_is_the_dataclass_defaults_but_for_its_listed_choices(name):
  module, cls = RUNS[name]
  preset = _flat(dataclasses.asdict(cls.from_config(module.get_config())))
  default = _flat(dataclasses.asdict(cls()))
  assert preset.keys() == default.keys()
  differing = {k: preset[k] for k in preset if preset[k] != default[k]}
  assert differing == CHOICES[name]


def test_the_paper_preset_is_the_papers_setup():
  paper = DiffusionRunConfig.from_config(diffusion.get_config("paper"))
  assert (paper.train.batch_size, paper.train.learning_rate, paper.train.num_epochs) == (
      256,
      2e-4,
      2000,
  )
  assert (paper.sampling.sampler, paper.sampling.steps, paper.sampling.mode) == (
      "ddim",
      10,
      "paper",
  )
  guidance = paper.sampling.guidance
  assert (guidance.t_c, guidance.w_max_base, guidance.w_min) == (50.0, 1.0, 0.1)
  assert (paper.diffusion.num_steps, paper.diffusion.conditioning) == (1000, "token")
  assert not paper.diffusion.intent_conditioning and paper.sampling.num_samples == 9
  # the paper's sampling is the dataclass default: nothing of it is a preset's choice
  assert paper.sampling == DiffusionRunConfig().sampling


def test_the_long_distillation_preset_lengthens_both_stages():
  epochs = lambda arg: DistillRunConfig.from_config(distill.get_config(arg)).train.num_epochs
  assert (epochs("demo"), epochs("demo,long")) == (2, 8)
  assert (epochs("demo,halving"), epochs("demo,long,halving")) == (10, 15)
  with pytest.raises(ValueError, match="'long' extends ':demo'"):
    distill.get_config("long")
