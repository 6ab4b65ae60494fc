"""Baselines from the last observed ego state (same frame as `Scenarios`): physics
extrapolations, and the token-mean controls that measure what a scenario token tells."""

import functools

import jax
import jax.numpy as jnp

from cvmdx_jax import constants, vmm


@jax.jit
def constant_velocity(xi):
  """Constant velocity: xi (M, 9, 75, 4) -> (M, 125, 2) ego positions after t0."""
  velocity = jnp.asarray(xi)[:, 0, -1, 2:4]
  t = constants.DT * jnp.arange(1, constants.T_PRED + 1)
  return velocity[:, None, :] * t[None, :, None]


@functools.partial(jax.jit, static_argnames="window")
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
  controls = jnp.broadcast_to(
      jnp.stack([accel, yaw_rate], -1)[:, None, :], (vel.shape[0], constants.T_PRED, 2)
  )
  return vmm.rollout(controls, speed[:, -1], heading[:, -1])


def token_mean(train_controls, train_tokens, tokens, v0, psi0, codebook_size: int):
  """Each token's mean training controls, rolled out from each scenario's own state.

  What a token-only model predicts for its mean when it matches p(controls | q) exactly
  (up to the rollout's curvature), so it scores how much the tokens tell about the
  future. Entries without training scenarios fall back to the mean over all of them.

  Args:
    train_controls: (M_train, 125, 2) [a_x m/s^2, yaw rate rad/s].
    train_tokens: (M_train,) int tokens of the training scenarios.
    tokens: (M,) int tokens of the scenarios to predict.
    v0, psi0: (M,) their speed [m/s] and heading [rad] at t0.
    codebook_size: Q.

  Returns:
    (M, 125, 2) positions after t0 [m].
  """
  train_controls = jnp.asarray(train_controls, jnp.float32)
  sums = jax.ops.segment_sum(train_controls, train_tokens, codebook_size)
  counts = jax.ops.segment_sum(jnp.ones(train_controls.shape[0]), train_tokens, codebook_size)
  means = jnp.where(
      counts[:, None, None] > 0,
      sums / jnp.maximum(counts, 1)[:, None, None],
      jnp.mean(train_controls, axis=0),
  )
  return vmm.rollout(means[jnp.asarray(tokens)], jnp.asarray(v0), jnp.asarray(psi0))
