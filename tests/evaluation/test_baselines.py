"""Baselines: closed forms for the physics extrapolations, a hand-worked token mean."""

import numpy as np

from cvmdx_jax import vmm
from cvmdx_jax.evaluation import baselines

DT = 0.04


def _history(v, psi, accel=0.0, yaw_rate=0.0):
  """xi (1, 9, 75, 4) whose ego drives with constant acceleration and yaw rate up to t0."""
  t = DT * np.arange(-74, 1)
  speed = v + accel * t
  heading = psi + yaw_rate * t
  xi = np.zeros((1, 9, 75, 4), np.float32)
  xi[0, 0, :, 2] = speed * np.cos(heading)
  xi[0, 0, :, 3] = speed * np.sin(heading)
  return xi


def test_constant_velocity_is_last_velocity_times_time():
  xi = _history(30.0, 0.05)
  out = np.asarray(baselines.constant_velocity(xi))
  t = DT * np.arange(1, 126)
  np.testing.assert_allclose(out[0, :, 0], 30.0 * np.cos(0.05) * t, rtol=1e-5)
  np.testing.assert_allclose(out[0, :, 1], 30.0 * np.sin(0.05) * t, rtol=1e-5)


def test_constant_acceleration_yaw_rate_recovers_both_and_rolls_them_out():
  xi = _history(25.0, 0.02, accel=-1.2, yaw_rate=0.03)
  out = np.asarray(baselines.constant_acceleration_yaw_rate(xi))
  expected = np.asarray(vmm.rollout(np.tile([-1.2, 0.03], (125, 1)), 25.0, 0.02))
  np.testing.assert_allclose(out[0], expected, atol=0.02)


def test_token_mean_rolls_out_each_tokens_mean_controls():
  train_controls = np.zeros((5, 125, 2), np.float32)
  train_controls[:2, :, 0] = [[1.0], [3.0]]  # token 0: a_x 1 and 3 -> mean 2
  train_controls[2:, :, 1] = 0.01  # token 2: yaw rate 0.01
  train_tokens = np.array([0, 0, 2, 2, 2])
  v0, psi0 = np.array([20.0, 30.0, 25.0]), np.array([0.0, 0.1, 0.0])
  out = np.asarray(
      baselines.token_mean(
          train_controls, train_tokens, np.array([0, 2, 1]), v0, psi0, codebook_size=3
      )
  )
  expected = [
      np.tile([2.0, 0.0], (125, 1)),
      np.tile([0.0, 0.01], (125, 1)),
      train_controls.mean(0),
  ]  # token 1 is unused: mean over all
  for i in range(3):
    np.testing.assert_allclose(
        out[i], np.asarray(vmm.rollout(expected[i], v0[i], psi0[i])), rtol=1e-5, atol=1e-4
    )
