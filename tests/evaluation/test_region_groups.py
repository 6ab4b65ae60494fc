"""Regions across recordings: leave-one-recording-out coverage by hand, a covariate that
carries the recordings' difference against one that does not, the covariates of t0."""

import types

import numpy as np
import pytest

from cvmdx_jax.evaluation import region_groups


def test_leave_one_out_hand_worked():
  u = np.array([0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.05, 0.95, 0.15, 0.25])
  recordings = np.repeat([7, 8, 9], 4)
  ids, counts, cover = region_groups.leave_one_out(np.stack([u, u], 1), recordings, level=0.5)
  # without 7: 5th of 8 (ceil(9 * 0.5)) = 0.6, all of 7 covered; without 8: 0.25, none of 8;
  # without 9: 0.5, three of 9 (0.05, 0.15, 0.25)
  np.testing.assert_array_equal(ids, [7, 8, 9])
  np.testing.assert_array_equal(counts, [4, 4, 4])
  np.testing.assert_allclose(cover, [[1.0, 1.0], [0.0, 0.0], [0.75, 0.75]])
  mean, largest = region_groups.errors(counts, cover, level=0.5)
  assert mean == pytest.approx((0.5 + 0.5 + 0.25) / 3) and largest == 0.5


def test_errors_weight_recordings_by_their_scenarios():
  mean, largest = region_groups.errors([1, 3], [[0.8, 1.0], [0.9, 0.9]])
  assert mean == pytest.approx((1 * (0.1 + 0.1) + 3 * 0.0) / (4 * 2)) and largest == pytest.approx(
      0.1
  )


def test_a_covariate_that_carries_the_recordings_difference_helps_a_random_one_does_not():
  rng = np.random.default_rng(0)
  # one value per recording, three recordings alike: a left-out one has two in its tercile
  difficulty = np.repeat([0.0, 0.05, 0.1, 0.5, 0.55, 0.6, 0.9, 0.95, 1.0], 300)
  recordings = np.repeat(np.arange(9), 300)
  u = rng.uniform(size=(len(difficulty), 1)) ** (1.0 / (0.3 + 3.0 * difficulty[:, None]))
  x = difficulty + rng.normal(0, 0.01, len(difficulty))
  plain = region_groups.errors(*region_groups.leave_one_out(u, recordings)[1:])
  grouped = region_groups.errors(*region_groups.leave_one_out(u, recordings, x)[1:])
  noise = region_groups.errors(
      *region_groups.leave_one_out(u, recordings, rng.normal(size=len(x)))[1:]
  )
  assert grouped[0] < 0.6 * plain[0] and grouped[1] < 0.6 * plain[1]
  assert noise[0] > 0.9 * plain[0]


def test_leave_one_out_needs_two_recordings():
  with pytest.raises(ValueError, match="2 recordings"):
    region_groups.leave_one_out(np.zeros((3, 1)), np.zeros(3))


def test_covariates_of_t0():
  mask = np.zeros((2, 9, 75), bool)
  xi = np.zeros((2, 9, 75, 4))
  mask[0, [1, 4], -1] = True
  xi[0, 1, -1, 2:] = [3.0, 4.0]  # speed 5
  xi[0, 4, -1, 2:] = [15.0, 0.0]
  mask[0, 2, -2] = True  # present before t0 only: not counted
  traj = np.zeros((2, 3, 125, 2))
  traj[0, :, -1, 1] = [0.0, 1.0, 2.0]
  scenarios = types.SimpleNamespace(mask=mask, xi=xi, v0=np.array([20.0, 25.0]))
  output = types.SimpleNamespace(
      delta=np.array([1.5, 2.5]), prediction=types.SimpleNamespace(trajectories=traj)
  )
  c = region_groups.covariates(scenarios, output)
  assert set(c) == set(region_groups.COVARIATES)
  np.testing.assert_allclose(c["neighbours"], [2, 0])
  np.testing.assert_allclose(c["neighbour_speed"], [10.0, 25.0])  # none: v0
  np.testing.assert_allclose(c["lateral_spread"], [np.std([0.0, 1.0, 2.0]), 0.0])
  np.testing.assert_allclose(c["delta"], [1.5, 2.5])


def test_recording_coverage():
  ids, counts, cover = region_groups.recording_coverage([1, 0, 1, 1], [5, 5, 2, 2])
  np.testing.assert_array_equal(ids, [2, 5])
  np.testing.assert_array_equal(counts, [2, 2])
  np.testing.assert_allclose(cover, [1.0, 0.5])
