"""k-means hypotheses: scikit-learn agreement, hand-worked sets, output contract."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from sklearn import cluster

from cvmdx_jax.config.fields import ConfigFieldError
from cvmdx_jax.config.sampling import HypothesisConfig
from cvmdx_jax.multimodal import gmm, hypotheses, kmeans, synthetic

KMEANS = HypothesisConfig(method="kmeans")
fit_hypotheses = jax.jit(hypotheses.fit_hypotheses, static_argnames=("c_max", "config"))
kmeans_fit = jax.jit(kmeans.fit, static_argnames=("num_clusters", "num_iters"))


def _trajectory_sets(seed, num_sets=20, n=36, t=125):
  """Samples of three overlapping modes (lateral offsets, speeds) per set, metres."""
  rng = np.random.default_rng(seed)
  time = np.arange(1, t + 1) * 0.04
  out = []
  for _ in range(num_sets):
    mode = rng.integers(0, 3, n)
    speed = 30 + rng.normal(0, 1.5, n) + 1.5 * mode
    lateral = 3.5 * (mode - 1)[:, None] * np.clip(time / 4, 0, 1) + rng.normal(0, 0.3, (n, 1))
    out.append(np.stack([speed[:, None] * time, lateral * np.ones_like(time)], axis=-1))
  return np.asarray(out, np.float32)


@pytest.mark.parametrize("endpoint_weight", [0.0, 0.5])
def test_agrees_with_sklearn_kmeans_from_the_same_seeds(endpoint_weight):
  sets = _trajectory_sets(0)
  for trajectories in sets:
    points = np.asarray(kmeans.features(trajectories, endpoint_weight))
    seeds = np.asarray(gmm.farthest_point_seeds(jnp.asarray(points), 3))
    ref = cluster.KMeans(
        3, init=points[seeds].astype(np.float64), n_init=1, max_iter=10, tol=0.0, algorithm="lloyd"
    ).fit(points.astype(np.float64))
    centers, labels = kmeans_fit(points, num_clusters=3, num_iters=10)
    np.testing.assert_array_equal(np.asarray(labels), ref.labels_)
    np.testing.assert_allclose(np.asarray(centers), ref.cluster_centers_, rtol=1e-4, atol=1e-3)


def test_farthest_point_seeds_are_the_hand_worked_ones():
  points = np.array([[0.0], [2.0], [3.0], [5.0], [9.0]], np.float32)
  # centroid 3.8: 9 is farthest; then 0 (9 from 9); then 5 (min distance 4 to {9, 0})
  seeds = gmm.farthest_point_seeds(jnp.asarray(points), 3)
  np.testing.assert_array_equal(np.asarray(seeds), [4, 0, 3])


def test_hand_worked_lloyd_steps():
  # seeds 9 and 0: {0, 2, 3} and {5, 9}; centres 5/3 and 7; then no point moves
  x = np.array([0.0, 2.0, 3.0, 5.0, 9.0], np.float32)
  trajectories = np.stack([x, np.zeros_like(x)], axis=-1)[None, :, None, :]  # T = 1
  h = fit_hypotheses(trajectories, config=dataclasses.replace(KMEANS, c_max=2))
  np.testing.assert_allclose(np.asarray(h.probs[0]), [0.6, 0.4], rtol=1e-6)
  np.testing.assert_allclose(np.asarray(h.means[0, :, 0, 0]), [5 / 3, 7.0], rtol=1e-6)
  np.testing.assert_array_equal(np.asarray(h.labels[0]), [0, 0, 0, 1, 1])
  assert int(h.num_modes[0]) == 2 and int(h.num_components[0]) == 2


def _assert_well_formed(h, trajectories):
  probs, means, labels = (np.asarray(a) for a in (h.probs, h.means, h.labels))
  assert np.all(np.isfinite(probs)) and np.all(np.isfinite(means))
  np.testing.assert_allclose(probs.sum(axis=1), 1.0, rtol=1e-6)
  assert np.all(np.diff(probs, axis=1) <= 0)
  for i in range(len(probs)):
    k = int(h.num_modes[i])
    assert np.all(probs[i, :k] > 0) and np.all(probs[i, k:] == 0) and np.all(means[i, k:] == 0)
    for slot in range(k):
      members = labels[i] == slot
      np.testing.assert_allclose(probs[i, slot], members.mean(), rtol=1e-6)
      np.testing.assert_allclose(
          means[i, slot], trajectories[i][members].mean(axis=0), rtol=1e-5, atol=1e-4
      )


def test_all_samples_identical_give_one_hypothesis():
  trajectories = np.broadcast_to(_trajectory_sets(1, num_sets=1)[:, :1], (1, 9, 125, 2))
  h = fit_hypotheses(np.ascontiguousarray(trajectories), config=KMEANS)
  _assert_well_formed(h, trajectories)
  assert int(h.num_modes[0]) == 1
  np.testing.assert_array_equal(np.asarray(h.probs[0]), [1.0, 0.0, 0.0])
  np.testing.assert_allclose(np.asarray(h.means[0, 0]), trajectories[0, 0], rtol=1e-6)


def test_duplicates_and_fewer_samples_than_k():
  base = _trajectory_sets(2, num_sets=1)[0]
  duplicated = base[[0, 0, 0, 5, 5, 7]][None]  # three distinct samples
  h = fit_hypotheses(duplicated, config=dataclasses.replace(KMEANS, c_max=5))
  _assert_well_formed(h, duplicated)
  assert int(h.num_modes[0]) == 3
  np.testing.assert_allclose(np.asarray(h.probs[0]), [0.5, 2 / 6, 1 / 6, 0, 0], rtol=1e-6)
  two = base[None, :2]  # N = 2 < K = 3
  h = fit_hypotheses(two, config=KMEANS)
  _assert_well_formed(h, two)
  np.testing.assert_allclose(np.asarray(h.probs[0]), [0.5, 0.5, 0.0], rtol=1e-6)


def test_contract_on_synthetic_sets():
  trajectories = synthetic.mode_sets(seed=3, num_sets=50)[0]
  h = fit_hypotheses(trajectories, config=KMEANS)
  _assert_well_formed(h, trajectories)
  assert h.means.shape == (50, 3, 125, 2) and h.labels.shape == (50, 9)
  assert np.all(np.asarray(h.num_components) == 3) and np.all(np.isnan(np.asarray(h.bic)))


def test_endpoint_weight_defines_the_distance():
  rng = np.random.default_rng(4)
  a, b = rng.normal(size=(2, 125, 2)).astype(np.float32)
  for weight in (0.0, 0.3, 1.0):
    w = np.asarray(kmeans.step_weights(125, weight))
    np.testing.assert_allclose(w.sum(), 1.0, rtol=1e-6)
    fa, fb = np.asarray(kmeans.features(np.stack([a, b]), weight))
    want = np.sum(w * np.sum((a - b) ** 2, axis=-1))
    np.testing.assert_allclose(np.sum((fa - fb) ** 2), want, rtol=1e-5)
  assert np.asarray(kmeans.step_weights(125, 1.0))[:-1].max() == 0


def test_bad_settings_are_refused():
  with pytest.raises(ValueError, match="method"):
    HypothesisConfig(method="medoids")
  with pytest.raises(ConfigFieldError, match="must be in") as error:
    HypothesisConfig(method="kmeans", endpoint_weight=1.5)
  assert error.value.field == "endpoint_weight"
  with pytest.raises(ConfigFieldError, match="must be >= 0") as error:
    HypothesisConfig(method="kmeans", kmeans_iters=-1)
  assert error.value.field == "kmeans_iters"
