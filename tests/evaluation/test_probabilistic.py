"""Energy score, mixture NLL and calibration against closed forms, scipy and hand-worked cases."""

import math

import jax.numpy as jnp
import numpy as np
from scipy import stats

from cvmdx_jax.evaluation import probabilistic


def _as_trajectories(x):
  """(..., N) scalars -> (..., N, 1, 2) one-step trajectories [x, 0]."""
  x = np.asarray(x, np.float32)
  return np.stack([x, np.zeros_like(x)], axis=-1)[..., None, :]


def test_energy_score_of_1d_gaussian_samples_is_the_closed_form():
  rng = np.random.default_rng(0)
  mu, sigma = 1.0, 2.0
  samples = rng.normal(mu, sigma, 4000)
  for y in (-3.0, 1.0, 2.5):
    z = (y - mu) / sigma
    # E|X - y| = sigma (2 phi(z) + z (2 Phi(z) - 1)), E|X - X'| = 2 sigma / sqrt(pi)
    want = sigma * (2 * stats.norm.pdf(z) + z * (2 * stats.norm.cdf(z) - 1)) - sigma / math.sqrt(
        math.pi
    )
    got = float(probabilistic.energy_score(_as_trajectories(samples), _as_trajectories([y])[0]))
    np.testing.assert_allclose(got, want, rtol=0.03, atol=0.02)


def test_energy_score_hand_worked_two_samples():
  a = np.zeros((2, 2), np.float32)
  b = np.array([[3.0, 0.0], [4.0, 0.0]], np.float32)  # rms distance from a: sqrt(12.5)
  samples = np.stack([a, b])
  # truth = a: (0 + sqrt(12.5)) / 2 - sqrt(12.5) / 2 = 0
  np.testing.assert_allclose(float(probabilistic.energy_score(samples, a)), 0.0, atol=1e-5)
  # truth [(0, 3), (0, 4)]: d(a, y) = sqrt(12.5), d(b, y) = sqrt((18 + 32) / 2) = 5
  y = np.array([[0.0, 3.0], [0.0, 4.0]], np.float32)
  np.testing.assert_allclose(float(probabilistic.energy_score(samples, y)), 2.5, rtol=1e-5)
  # one sample: the distance to the truth
  np.testing.assert_allclose(float(probabilistic.energy_score(b[None], y)), 5.0, rtol=1e-6)


def test_energy_score_is_lowest_for_the_true_distribution():
  rng = np.random.default_rng(1)
  t, n, draws = 4, 200, 400
  true_sd = np.array([1.0, 0.3])
  truths = rng.normal(0.0, 1.0, (draws, t, 2)) * true_sd

  def mean_score(shift, scale):
    samples = shift + scale * rng.normal(0.0, 1.0, (draws, n, t, 2)) * true_sd
    return float(
        jnp.mean(probabilistic.energy_score(samples.astype(np.float32), truths.astype(np.float32)))
    )

  truth = mean_score(0.0, 1.0)
  for shift, scale in ((0.5, 1.0), (0.0, 0.5), (0.0, 2.0)):
    assert truth < mean_score(shift, scale)


def test_hypothesis_covariances_and_nll_agree_with_numpy_and_scipy():
  rng = np.random.default_rng(2)
  points = (rng.normal(size=(11, 2)) * [3.0, 0.5]).astype(np.float32)
  labels = np.array([0, 0, 0, 0, 1, 1, 1, 0, 1, 2, 0])  # slot 2: a singleton, slot 3: empty
  probs = np.bincount(labels, minlength=4) / len(labels)
  means, cov = probabilistic.hypothesis_covariances(points, labels, 4)
  floor = probabilistic.COVARIANCE_FLOOR_M2
  for k in range(3):
    members = points[labels == k]
    np.testing.assert_allclose(means[k], members.mean(axis=0), rtol=1e-5)
    want = np.cov(members.T, bias=True) if len(members) > 1 else np.zeros((2, 2))
    np.testing.assert_allclose(cov[k], want + floor * np.eye(2), rtol=1e-5, atol=1e-6)
  for y in (np.array([0.5, -0.2]), np.array([8.0, 2.0])):
    density = sum(
        probs[k]
        * stats.multivariate_normal(
            np.asarray(means[k], np.float64), np.asarray(cov[k], np.float64)
        ).pdf(y)
        for k in range(3)
    )
    got = float(
        probabilistic.mixture_nll(
            means, cov, jnp.asarray(probs, jnp.float32), jnp.asarray(y, jnp.float32)
        )
    )
    np.testing.assert_allclose(got, -np.log(density), rtol=1e-4)


def test_final_position_nll_reads_the_5s_positions():
  rng = np.random.default_rng(3)
  samples = rng.normal(size=(2, 9, 5, 2)).astype(np.float32)
  labels = np.array([[0, 1, 0, 1, 0, 1, 0, 1, 2]] * 2)
  probs = np.array([[4, 4, 1]] * 2, np.float32) / 9
  gt = rng.normal(size=(2, 5, 2)).astype(np.float32)
  got = np.asarray(probabilistic.final_position_nll(samples, labels, probs, gt))
  for i in range(2):
    means, cov = probabilistic.hypothesis_covariances(samples[i, :, -1], labels[i], 3)
    want = probabilistic.mixture_nll(means, cov, probs[i], gt[i, -1])
    np.testing.assert_allclose(got[i], float(want), rtol=1e-6)


def test_reliability_and_ece_hand_worked():
  probs = np.array([[0.6, 0.4, 0.0], [0.9, 0.1, 0.0], [1.0, 0.0, 0.0]], np.float32)
  closest = np.array([0, 1, 0])
  correct = np.arange(3)[None] == closest[:, None]
  rel = probabilistic.reliability(probs, correct, probs > 0)
  np.testing.assert_array_equal(np.asarray(rel.count), [0, 1, 0, 0, 1, 0, 1, 0, 0, 2])
  np.testing.assert_array_equal(np.asarray(rel.correct), [0, 1, 0, 0, 0, 0, 1, 0, 0, 1])
  np.testing.assert_allclose(
      np.asarray(rel.confidence)[[1, 4, 6, 9]], [0.1, 0.4, 0.6, 1.9], rtol=1e-6
  )
  # |1 - 0.1| + |0 - 0.4| + |1 - 0.6| + |1 - 1.9| over 5 hypotheses
  np.testing.assert_allclose(
      float(probabilistic.expected_calibration_error(rel)), (0.9 + 0.4 + 0.4 + 0.9) / 5, rtol=1e-6
  )
  certain = probabilistic.reliability(
      np.ones((4, 1), np.float32), np.ones((4, 1), bool), np.ones((4, 1), bool)
  )
  assert float(probabilistic.expected_calibration_error(certain)) == 0.0
