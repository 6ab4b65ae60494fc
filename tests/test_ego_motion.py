"""Ego-motion features against hand-worked trajectories (closed forms)."""

import numpy as np
import pytest

from cvmdx_jax import constants, ego_motion

DT, T = constants.DT, constants.T_OBS
TAU = DT * (np.arange(T) - (T - 1))  # observed times relative to t0: -2.96 .. 0 s
WINDOW = (T - 1) * DT


def _scenario(x, y, vx, vy):
  """One scenario holding only the ego: (1, 9, 75, 4) xi and (1, 9, 75) mask."""
  xi = np.zeros((1, constants.NUM_VEHICLES, T, 4), np.float32)
  xi[0, 0] = np.stack([x - x[-1], y - y[-1], vx, vy], -1)
  mask = np.zeros((1, constants.NUM_VEHICLES, T), bool)
  mask[0, 0] = True
  return xi, mask


def _raw(features):
  """Undoes the documented normalisation (exact inside the clip range)."""
  centre = np.array([c for _, c, _ in ego_motion.FEATURES])
  scale = np.array([s for _, _, s in ego_motion.FEATURES])
  return np.asarray(features)[0] * scale + centre


def _no_neighbours(raw):
  # lane reference, leader flag, gap (150 m when no leader), closing speed
  np.testing.assert_allclose(raw[8:13], [0.0, 0.0, 0.0, 150.0, 0.0], atol=1e-5)
  # per other neighbour: absent, put 150 m ahead / behind or alongside, no speed, no offset
  expected = [[0.0, 150.0 * side, 0.0, 0.0] for _, side in ego_motion.NEIGHBOURS]
  np.testing.assert_allclose(raw[13:].reshape(-1, 4), expected, atol=1e-5)


def test_constant_speed_straight():
  v = 27.0
  xi, mask = _scenario(v * TAU, np.zeros(T), np.full(T, v), np.zeros(T))
  raw = _raw(ego_motion.ego_features(xi, mask))
  np.testing.assert_allclose(raw[:8], [v, 0, 0, 0, 0, 0, 0, 0], atol=1e-5)
  _no_neighbours(raw)


def test_constant_acceleration():
  v0, a = 31.0, -1.5  # speed at t0, m/s^2
  speed = v0 + a * TAU
  xi, mask = _scenario(v0 * TAU + 0.5 * a * TAU**2, np.zeros(T), speed, np.zeros(T))
  raw = _raw(ego_motion.ego_features(xi, mask))
  np.testing.assert_allclose(raw[:3], [v0, a, a], atol=1e-4)
  np.testing.assert_allclose(raw[3:8], 0.0, atol=1e-5)


def test_constant_yaw_rate_arc():
  v, psi0, r = 30.0, 0.02, -0.012  # m/s, heading at t0 [rad], yaw rate [rad/s]
  psi = psi0 + r * TAU
  x = v / r * (np.sin(psi) - np.sin(psi0))
  y = -v / r * (np.cos(psi) - np.cos(psi0))
  xi, mask = _scenario(x, y, v * np.cos(psi), v * np.sin(psi))
  raw = _raw(ego_motion.ego_features(xi, mask))
  shift = lambda s: v / r * (np.cos(psi0 - r * s) - np.cos(psi0))  # y(t0) - y(t0 - s)
  np.testing.assert_allclose(raw[[0, 1, 2]], [v, 0, 0], atol=1e-4)
  np.testing.assert_allclose(raw[3], r, atol=2e-5)
  np.testing.assert_allclose(raw[4], psi0, atol=1e-6)
  np.testing.assert_allclose(raw[5], v * np.sin(psi0), atol=1e-5)
  np.testing.assert_allclose(raw[6:8], [shift(1.0), shift(WINDOW)], atol=1e-4)
  _no_neighbours(raw)


def test_neighbours_give_lane_offset_and_leader():
  xi, mask = _scenario(30.0 * TAU, np.zeros(T), np.full(T, 30.0), np.zeros(T))
  preceding = constants.VEHICLE_SLOTS.index("preceding")
  following = constants.VEHICLE_SLOTS.index("following")
  xi[0, preceding, -1] = [42.0, 0.3, 27.5, 0.0]
  xi[0, following, -1] = [-20.0, 0.5, 31.0, 0.0]
  mask[0, (preceding, following), -1] = True
  raw = _raw(ego_motion.ego_features(xi, mask))
  # ego y = 0; lane centre = mean(0.3, 0.5); leader 42 m ahead, 2.5 m/s slower
  np.testing.assert_allclose(raw[8:13], [-0.4, 1.0, 1.0, 42.0, -2.5], atol=1e-5)
  following_row = 13 + 4 * [slot for slot, _ in ego_motion.NEIGHBOURS].index("following")
  np.testing.assert_allclose(
      raw[following_row : following_row + 4], [1.0, -20.0, 1.0, 0.5], atol=1e-5
  )
  mask[0, following, -1] = False  # one same-lane neighbour is enough
  np.testing.assert_allclose(_raw(ego_motion.ego_features(xi, mask))[8], -0.3, atol=1e-5)


def test_side_neighbours_offsets_and_clip():
  xi, mask = _scenario(30.0 * TAU, np.zeros(T), np.full(T, 30.0), np.zeros(T))
  xi[0, 0, -1, 1] = 0.2  # the ego 0.2 m left of its origin at t0
  placed = {
      "leftPreceding": [35.0, 3.9, 33.0, 0.1],
      "rightFollowing": [-400.0, -3.5, 29.0, 0.0],
      "leftAlongside": [-1.0, 3.7, 30.5, 0.0],
  }
  for slot, state in placed.items():
    xi[0, constants.VEHICLE_SLOTS.index(slot), -1] = state
    mask[0, constants.VEHICLE_SLOTS.index(slot), -1] = True
  raw = _raw(ego_motion.ego_features(xi, mask))[13:].reshape(-1, 4)
  rows = {slot: row for (slot, _), row in zip(ego_motion.NEIGHBOURS, raw)}
  np.testing.assert_allclose(rows["leftPreceding"], [1.0, 35.0, 3.0, 3.7], atol=1e-5)
  np.testing.assert_allclose(rows["leftAlongside"], [1.0, -1.0, 0.5, 3.5], atol=1e-5)
  # 400 m behind is clipped to the 150 m of "nobody there"; -3.5 - 0.2 = -3.7 m
  np.testing.assert_allclose(rows["rightFollowing"], [1.0, -150.0, -1.0, -3.7], atol=1e-5)
  np.testing.assert_allclose(rows["rightPreceding"], [0.0, 150.0, 0.0, 0.0], atol=1e-5)


def test_short_history_uses_only_observed_steps():
  v0, a, first = 25.0, 0.8, 60  # ego observed from step 60 on only
  speed = v0 + a * TAU
  xi, mask = _scenario(v0 * TAU + 0.5 * a * TAU**2, np.zeros(T), speed, np.zeros(T))
  xi[0, 0, :first], mask[0, 0, :first] = 0.0, False
  raw = _raw(ego_motion.ego_features(xi, mask))
  np.testing.assert_allclose(raw[:3], [v0, a, a], atol=1e-4)


def test_clipped_and_deterministic():
  xi, mask = _scenario(90.0 * TAU, np.zeros(T), np.full(T, 90.0), np.zeros(T))
  f = ego_motion.ego_features(xi, mask)
  assert f.shape == (1, ego_motion.NUM_FEATURES) and f.dtype == np.float32
  assert float(f[0, 0]) == ego_motion.CLIP  # (90 - 30) / 10 = 6 -> 5
  np.testing.assert_array_equal(f, ego_motion.ego_features(xi, mask))


def test_residual_controls_closed_form():
  ego = np.zeros((2, ego_motion.NUM_FEATURES), np.float32)
  ego[:, 1] = [1.2, -0.5]  # m/s^2 (scale 1)
  ego[:, 3] = [0.5, 1.0]  # x 0.02 rad/s
  base = np.asarray(ego_motion.residual_controls(ego, (1.0, np.inf)))
  t = DT * np.arange(constants.T_PRED)
  assert base.shape == (2, constants.T_PRED, 2)
  np.testing.assert_allclose(base[:, :, 0], np.outer([1.2, -0.5], np.exp(-t)), rtol=1e-5)
  np.testing.assert_allclose(base[:, :, 1], np.outer([0.01, 0.02], np.ones_like(t)), rtol=1e-5)


def test_conditioning_names():
  assert ego_motion.uses_film("ego_film") and not ego_motion.uses_residual("ego_film")
  assert ego_motion.uses_residual("ego_residual") and not ego_motion.uses_film("ego_residual")
  assert ego_motion.uses_film("ego_film_residual") and ego_motion.uses_residual("ego_film_residual")
  assert not ego_motion.uses_film("token") and not ego_motion.uses_residual("token")
  with pytest.raises(ValueError, match="diffusion.conditioning"):
    ego_motion.check_conditioning("film")
