"""Split-conformal levels and hypothesis sets: hand-worked cases and the coverage guarantee."""

import numpy as np
import pytest

from cvmdx_jax.evaluation import conformal


def test_calibrated_level_hand_worked():
  scores = np.arange(1, 11) / 10.0
  assert conformal.calibrated_level(scores, 0.5) == 0.6  # ceil(11 * 0.5) = 6th
  assert conformal.calibrated_level(scores, 0.95) == 1.0  # ceil(11 * 0.95) = 11 > 10


def test_calibration_restores_coverage_of_overconfident_scores():
  rng = np.random.default_rng(0)
  val, test = rng.beta(0.5, 1.0, 2000), rng.beta(0.5, 1.0, 20000)  # u skewed: miscalibrated
  level = conformal.calibrated_level(val, 0.9)
  assert abs(np.mean(test <= 0.9) - 0.9) > 0.02
  assert abs(np.mean(test <= level) - 0.9) < 0.015


def test_mondrian_levels_grow_with_the_bin_scale():
  rng = np.random.default_rng(1)
  delta = rng.uniform(0, 3, 3000)
  scores = np.clip(rng.uniform(0, 1, 3000) * (0.3 + delta / 3.0), 0, 1)
  lv = conformal.mondrian_levels(scores, delta, np.array([0.1, 1.5, 2.9]), (0.9,))
  assert lv.shape == (3, 1) and lv[0, 0] < lv[1, 0] < lv[2, 0]


def test_hypothesis_scores_and_sets():
  probs = np.array([[0.2, 0.5, 0.3, 0.0], [0.7, 0.3, 0.0, 0.0]])
  np.testing.assert_allclose(conformal.hypothesis_scores(probs, np.array([0, 0])), [1.0, 0.7])
  np.testing.assert_allclose(conformal.hypothesis_scores(probs, np.array([2, 1])), [0.8, 1.0])
  np.testing.assert_array_equal(conformal.hypothesis_set_size(probs, 0.75), [2, 2])
  np.testing.assert_array_equal(conformal.hypothesis_set_size(probs, 0.5), [1, 1])


def test_online_levels_hand_worked_with_delay():
  # times 0, 1, 2, 3; delay 2: scenario 0's miss arrives at 2, scenario 1's at 3
  u = np.array([0.95, 0.5, 0.2, 0.99])
  levels = conformal.online_levels(u, [0, 1, 2, 3], 2, 0.9, 0.9, 0.1)
  # 0: 0.9 (u 0.95 misses); 1: 0.9 (covered); 2: 0.9 + 0.1 (1 - 0.1) = 0.99;
  # 3: 0.99 + 0.1 (0 - 0.1) = 0.98
  np.testing.assert_allclose(levels, [0.9, 0.9, 0.99, 0.98])
  # the input's order is kept when times are shuffled
  perm = np.array([2, 0, 3, 1])
  np.testing.assert_allclose(
      conformal.online_levels(u[perm], np.arange(4)[perm], 2, 0.9, 0.9, 0.1), levels[perm]
  )


def test_online_levels_are_capped_and_constant_without_step():
  u = np.ones(50)
  np.testing.assert_allclose(conformal.online_levels(u, np.arange(50), 0, 0.8, 0.9, 0.0), 0.8)
  assert conformal.online_levels(u, np.arange(50), 0, 0.8, 0.9, 0.5).max() == conformal.LEVEL_CAP


def test_aci_gamma_meets_its_bound():
  gamma = conformal.aci_gamma(0.93, 3000)
  assert abs((0.93 + gamma) / (gamma * 3000) - conformal.ACI_TOLERANCE) < 1e-12
  with pytest.raises(ValueError, match="cannot bound"):
    conformal.aci_gamma(0.9, 50)


@pytest.mark.parametrize("delay", [0, 40])
def test_online_levels_recover_coverage_on_a_shifted_stream(delay):
  # calibrated where u is uniform; the stream's scores are larger (a harder road) and drift
  rng = np.random.default_rng(2)
  start = conformal.calibrated_level(rng.uniform(size=2000), 0.9)
  m = 3000
  u = rng.beta(1.0, 0.4 + 0.4 * np.linspace(0, 1, m))  # P(u <= start) ~0.6-0.75
  assert np.mean(u <= start) < 0.8
  levels = conformal.online_levels(
      u, np.arange(m), delay, start, 0.9, conformal.aci_gamma(start, m)
  )
  # the bound holds without delay; a delay of 40 scenarios costs little more here
  assert abs(np.mean(u <= levels) - 0.9) <= conformal.ACI_TOLERANCE + 0.005 * (delay > 0)
