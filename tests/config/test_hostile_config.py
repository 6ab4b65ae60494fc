"""Config values that used to train and fail only later (or in flax) are refused when the
typed config is built, naming the dotted field: sample counts that are not whole numbers
or too large, more hypothesis components than samples, a one-step diffusion, U-Net levels
that do not exist or channels that heads or groups do not divide."""

import numpy as np
import pytest

from configs import diffusion as diffusion_config
from cvmdx_jax.config.denoiser import DenoiserConfig
from cvmdx_jax.config.fields import ConfigFieldError
from cvmdx_jax.config.models import UNetConfig
from cvmdx_jax.config.runs import DiffusionRunConfig
from cvmdx_jax.config.sampling import MAX_SAMPLES, HypothesisConfig, SamplingConfig


@pytest.mark.parametrize(
    "kwargs, field, problem",
    [
        ({"num_samples": 9.5}, "num_samples", "whole number"),
        ({"num_samples": "9"}, "num_samples", "whole number"),
        ({"num_samples": True}, "num_samples", "whole number"),
        ({"steps": 2.5}, "steps", "whole number"),
        ({"num_samples": MAX_SAMPLES + 1}, "num_samples", f"<= {MAX_SAMPLES}"),
        ({"num_samples": 1_000_000}, "num_samples", f"<= {MAX_SAMPLES}"),
        (
            {"num_samples": 2, "hypotheses": HypothesisConfig(c_max=3)},
            "hypotheses.c_max",
            "num_samples=2",
        ),
    ],
)
def test_sampling_config_refuses(kwargs, field, problem):
  with pytest.raises(ConfigFieldError) as info:
    SamplingConfig(**kwargs)
  assert info.value.field == field and problem in info.value.problem


def test_sampling_config_takes_numpy_and_whole_float_integers():
  config = SamplingConfig(num_samples=np.int64(9), steps=np.int32(3))
  assert (config.num_samples, config.steps) == (9, 3)
  assert type(config.num_samples) is int and type(config.steps) is int
  assert SamplingConfig(num_samples=12.0).num_samples == 12
  assert SamplingConfig(num_samples=MAX_SAMPLES, hypotheses=HypothesisConfig(c_max=3))


@pytest.mark.parametrize(
    "kwargs, field",
    [
        ({"num_heads": 3}, "num_heads"),  # 128 channels: 3 heads do not divide them
        ({"base_channels": 96, "channel_mult": (1, 2, 3, 4), "num_heads": 5}, "num_heads"),
        ({"attention_levels": (7,)}, "attention_levels"),
        ({"channel_mult": (1, 2), "attention_levels": (2,)}, "attention_levels"),
        ({"channel_mult": ()}, "channel_mult"),
        ({"groups": 7}, "groups"),
    ],
)
def test_unet_config_refuses(kwargs, field):
  with pytest.raises(ConfigFieldError) as info:
    UNetConfig(**kwargs)
  assert info.value.field == field


def test_unet_heads_need_only_divide_the_attended_levels():
  # 8 x (1, 3, 4): 24 channels at level 1 (no attention there), 32 at levels 2 (attended)
  config = UNetConfig(
      base_channels=8,
      channel_mult=(1, 3, 4),
      attention_levels=(2,),
      num_heads=8,
      groups=8,
      padded_length=128,
  )
  assert config.num_heads == 8
  with pytest.raises(ConfigFieldError, match="num_heads"):
    UNetConfig(
        base_channels=8,
        channel_mult=(1, 3, 4),
        attention_levels=(1,),
        num_heads=16,
        groups=8,
        padded_length=128,
    )


def test_a_one_step_diffusion_is_refused():
  with pytest.raises(ConfigFieldError) as info:
    DenoiserConfig(num_steps=1)
  assert info.value.field == "num_steps" and ">= 2" in info.value.problem
  assert DenoiserConfig(num_steps=2).num_steps == 2


@pytest.mark.parametrize(
    "override, field",
    [
        (("model", "num_heads", 3), "model.num_heads"),
        (("model", "attention_levels", (7,)), "model.attention_levels"),
        (("diffusion", "num_steps", 1), "diffusion.num_steps"),
    ],
)
def test_the_run_config_names_the_dotted_field(override, field):
  config = diffusion_config.get_config("tiny")
  section, name, value = override
  config[section][name] = value
  with pytest.raises(ConfigFieldError) as info:
    DiffusionRunConfig.from_config(config)
  assert info.value.field == field
