"""Physics baselines from the last observed ego state (same frame as `Scenarios`)."""

import jax.numpy as jnp

from cvmdx_jax import constants, vmm


def constant_velocity(xi):
  """Constant velocity: xi (M, 9, 75, 4) -> (M, 125, 2) ego positions after t0."""
  velocity = jnp.asarray(xi)[:, 0, -1, 2:4]
  t = constants.DT * jnp.arange(1, constants.T_PRED + 1)
  return velocity[:, None, :] * t[None, :, None]


def constant_acceleration_yaw_rate(xi, window: int = 10):
  """Constant longitudinal acceleration and yaw rate, both estimated by finite
  differences of speed and heading over the last `window` observed steps, rolled
  out with the VMM. xi (M, 9, 75, 4) -> (M, 125, 2)."""
  vel = jnp.asarray(xi)[:, 0, -window:, 2:4]
  speed = jnp.linalg.norm(vel, axis=-1)
  heading = jnp.unwrap(jnp.arctan2(vel[..., 1], vel[..., 0]), axis=-1)
  span = (window - 1) * constants.DT
  accel = (speed[:, -1] - speed[:, 0]) / span
  yaw_rate = (heading[:, -1] - heading[:, 0]) / span
  controls = jnp.broadcast_to(jnp.stack([accel, yaw_rate], -1)[:, None, :],
                              (vel.shape[0], constants.T_PRED, 2))
  return vmm.rollout(controls, speed[:, -1], heading[:, -1])

