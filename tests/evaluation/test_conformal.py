"""Split-conformal levels and hypothesis sets: hand-worked cases and the coverage guarantee."""

import numpy as np

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


def test_delta_levels_grow_with_the_bin_scale():
  rng = np.random.default_rng(1)
  delta = rng.uniform(0, 3, 3000)
  scores = np.clip(rng.uniform(0, 1, 3000) * (0.3 + delta / 3.0), 0, 1)
  lv = conformal.delta_levels(scores, delta, np.array([0.1, 1.5, 2.9]), (0.9,))
  assert lv.shape == (3, 1) and lv[0, 0] < lv[1, 0] < lv[2, 0]


def test_hypothesis_scores_and_sets():
  probs = np.array([[0.2, 0.5, 0.3, 0.0], [0.7, 0.3, 0.0, 0.0]])
  np.testing.assert_allclose(conformal.hypothesis_scores(probs, np.array([0, 0])), [1.0, 0.7])
  np.testing.assert_allclose(conformal.hypothesis_scores(probs, np.array([2, 1])), [0.8, 1.0])
  np.testing.assert_array_equal(conformal.hypothesis_set_size(probs, 0.75), [2, 2])
  np.testing.assert_array_equal(conformal.hypothesis_set_size(probs, 0.5), [1, 1])
