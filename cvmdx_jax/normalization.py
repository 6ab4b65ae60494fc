"""Normalisation of the control targets x0 = [a_x, yaw_rate]."""

import jax.numpy as jnp
import numpy as np

from cvmdx_jax import constants

_SCALE = np.array([constants.ACCEL_SCALE, constants.YAW_RATE_SCALE], np.float32)


def normalize_controls(controls):
  """(..., T, 2) [m/s^2, rad/s] -> (..., T, 2) in [-1, 1] (clipped)."""
  return jnp.clip(controls / _SCALE, -1.0, 1.0)


def denormalize_controls(x0):
  """(..., T, 2) normalised controls -> physical [m/s^2, rad/s]."""
  return x0 * _SCALE
