"""Vehicle-bootstrap paired differences: grouping, verdicts, and the interval's width."""

import numpy as np

from cvmdx_jax.evaluation import intervals


def test_vehicle_groups_pair_recording_and_track():
  g = intervals.vehicle_groups([1, 1, 2, 1], [5, 5, 5, 6])
  assert g[0] == g[1] and len({g[0], g[2], g[3]}) == 3


def test_clear_difference_is_better_and_noise_is_a_tie():
  rng = np.random.default_rng(0)
  groups = np.repeat(np.arange(200), 3)
  b = rng.normal(1.0, 0.1, 600)
  row = intervals.paired_difference(b - 0.5, b, groups)
  assert row["verdict"] == "better" and abs(row["difference"] + 0.5) < 1e-9
  assert intervals.paired_difference(b + 0.5, b, groups)["verdict"] == "worse"
  noise = intervals.paired_difference(
      b + rng.normal(0, 0.1, 600), b + rng.normal(0, 0.1, 600), groups
  )
  assert noise["low"] < 0 < noise["high"] and noise["verdict"] == "tie"


def test_correlated_windows_widen_the_interval():
  """One value per vehicle repeated 10 times: the interval is that of 50 vehicles (SE of
  the mean of 50 unit-variance differences ~ 0.14), not of 500 windows (~0.045)."""
  rng = np.random.default_rng(1)
  per_vehicle = np.repeat(rng.normal(0, 1, 50), 10)
  row = intervals.paired_difference(per_vehicle, np.zeros(500), np.repeat(np.arange(50), 10))
  width = row["high"] - row["low"]
  assert 0.35 < width < 0.75  # 2 x 1.96 x 1 / sqrt(50) = 0.55


def test_rmse_statistic():
  row = intervals.paired_difference([3.0, 4.0], [0.0, 0.0], [0, 1], kind="rmse", draws=10)
  np.testing.assert_allclose(row["a"], np.sqrt(12.5))
  assert intervals.format_difference(row).endswith(row["verdict"])


def test_relative_difference_is_the_ratio_of_the_statistics_with_its_interval():
  rng = np.random.default_rng(2)
  groups = np.repeat(np.arange(300), 2)
  b = rng.gamma(4.0, 0.25, 600)  # per-scenario errors of mean 1 m
  row = intervals.paired_difference(1.03 * b, b, groups)
  # a / b - 1 is 0.03 in every replicate: the interval collapses onto it
  np.testing.assert_allclose([row["relative"], row["relative_low"], row["relative_high"]], 0.03)
  noisy = intervals.paired_difference(1.03 * b + rng.normal(0, 0.2, 600), b, groups)
  assert noisy["relative_low"] < noisy["relative"] < noisy["relative_high"]
  np.testing.assert_allclose(noisy["relative"], noisy["a"] / noisy["b"] - 1.0)
  # the absolute interval over b's mean brackets the relative one to first order
  assert abs(noisy["relative_low"] - noisy["low"] / noisy["b"]) < 0.01
  zero = intervals.paired_difference([1.0, 2.0], [0.0, 0.0], [0, 1], draws=10)
  assert np.isnan(zero["relative"]) and np.isnan(zero["relative_high"])
