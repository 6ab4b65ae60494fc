"""What a denoiser predicts: its settings (`DenoiserConfig`) and the control normalisation.

The targets are x0 = clip([a_x, yaw_rate] / control_scale, -1, 1) (the paper divides by
(4 m/s^2, 0.7 rad/s)); with an `ego_*residual` conditioning, of the controls minus the
ego's extrapolated current controls (`ego_motion.residual_controls`). The same settings
make the training targets (`train.diffusion`) and turn samples back into physical
controls (`inference.sampling`), so they are a property of the trained denoiser and are
stored with it (`config.json`, section `diffusion`).
"""

import jax.numpy as jnp

from cvmdx_jax.config.denoiser import PAPER_SCALE


def normalize_controls(controls, scale=PAPER_SCALE):
  """(..., T, 2) [m/s^2, rad/s] -> (..., T, 2) in [-1, 1] (clipped)."""
  return jnp.clip(controls / jnp.asarray(scale, jnp.float32), -1.0, 1.0)


def denormalize_controls(x0, scale=PAPER_SCALE):
  """(..., T, 2) normalised controls -> physical [m/s^2, rad/s]."""
  return x0 * jnp.asarray(scale, jnp.float32)
