"""Tiny networks the tests share: a U-Net of 16 channels on two levels that trains and
samples in seconds, and random inputs of the learned baselines' MLPs."""

import jax.numpy as jnp
import numpy as np

from cvmdx_jax import ego_motion
from cvmdx_jax.config.models import UNetConfig

_UNET = {
    "base_channels": 16,
    "channel_mult": (1, 2),
    "groups": 8,
    "attention_levels": (1,),
    "num_heads": 2,
}


def unet_config(num_tokens: int = 4, **overrides) -> UNetConfig:
  """The tiny U-Net for `num_tokens` tokens: 16 base channels on levels (1, 2), 8 groups, two
  attention heads at level 1; `overrides` replace or add fields."""
  return UNetConfig(num_tokens=num_tokens, **{**_UNET, **overrides})


def mlp_inputs(b: int = 4, seed: int = 0, num_tokens: int = 5) -> dict:
  """Random inputs of a learned baseline's MLP for `b` scenarios: tokens q, uncertainty
  delta, ego-motion features, v0 (m/s) and psi0 (rad, zero)."""
  rng = np.random.default_rng(seed)
  return {
      "q": jnp.asarray(rng.integers(0, num_tokens, b), jnp.int32),
      "delta": jnp.asarray(rng.uniform(0, 9, b), jnp.float32),
      "ego": jnp.asarray(rng.normal(size=(b, ego_motion.NUM_FEATURES)), jnp.float32),
      "v0": jnp.asarray(rng.uniform(20, 30, b), jnp.float32),
      "psi0": jnp.zeros(b, jnp.float32),
  }
