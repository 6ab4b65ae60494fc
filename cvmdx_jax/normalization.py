"""Normalisation of the control targets x0 = [a_x, yaw_rate].

The paper divides by (4 m/s^2, 0.7 rad/s) and clips to [-1, 1]; the scale is a
setting of a trained denoiser (`diffusion.control_scale`), used both to make its
targets and to turn its samples back into physical controls.
"""

import jax.numpy as jnp

from cvmdx_jax import constants

PAPER_SCALE = (constants.ACCEL_SCALE, constants.YAW_RATE_SCALE)


def normalize_controls(controls, scale=PAPER_SCALE):
  """(..., T, 2) [m/s^2, rad/s] -> (..., T, 2) in [-1, 1] (clipped)."""
  return jnp.clip(controls / jnp.asarray(scale, jnp.float32), -1.0, 1.0)


def denormalize_controls(x0, scale=PAPER_SCALE):
  """(..., T, 2) normalised controls -> physical [m/s^2, rad/s]."""
  return x0 * jnp.asarray(scale, jnp.float32)
