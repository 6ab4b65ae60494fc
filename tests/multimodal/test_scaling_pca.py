"""Scaling and batched PCA against scikit-learn."""

import jax.numpy as jnp
import numpy as np
import pytest
from sklearn import decomposition, preprocessing

from cvmdx_jax.multimodal import pca, scaling


def test_minmax_matches_sklearn_per_scenario():
  rng = np.random.default_rng(0)
  trajectories = rng.normal(size=(3, 9, 125, 2)) * [40.0, 2.0] + [30.0, 0.5]
  got = np.asarray(scaling.minmax_scale(jnp.asarray(trajectories, jnp.float32)))
  for b in range(3):
    want = preprocessing.MinMaxScaler().fit_transform(trajectories[b].reshape(-1, 2))
    np.testing.assert_allclose(got[b].reshape(-1, 2), want, atol=2e-6)


def test_minmax_constant_coordinate_maps_to_zero():
  trajectories = np.zeros((1, 9, 125, 2), np.float32)
  trajectories[..., 0] = np.linspace(0.0, 150.0, 125)  # y is constant 0
  got = np.asarray(scaling.minmax_scale(jnp.asarray(trajectories)))
  assert np.all(np.isfinite(got))
  np.testing.assert_array_equal(got[..., 1], 0.0)
  np.testing.assert_allclose(got[0, 0, -1, 0], 1.0)


def test_physical_scale_divides_by_metres():
  got = scaling.scale(jnp.asarray([[180.0, 7.0], [90.0, -3.5]]), "physical")
  np.testing.assert_allclose(np.asarray(got), [[1.0, 1.0], [0.5, -0.5]])


def test_unknown_scaling_raises():
  with pytest.raises(ValueError, match="scaling"):
    scaling.scale(jnp.zeros((1, 9, 4, 2)), "zscore")


def test_pca_scores_match_sklearn_up_to_sign():
  rng = np.random.default_rng(1)
  points = rng.normal(size=(4, 9, 250)) * np.linspace(3.0, 0.1, 250)
  got = np.asarray(pca.project(jnp.asarray(points, jnp.float32), 2))
  for b in range(4):
    want = decomposition.PCA(n_components=2, svd_solver="full").fit_transform(points[b])
    signs = np.sign(np.sum(got[b] * want, axis=0))
    np.testing.assert_allclose(got[b] * signs, want, atol=1e-4 * np.abs(want).max())


def test_pca_dim_out_of_range_raises():
  with pytest.raises(ValueError, match="pca_dim"):
    pca.project(jnp.zeros((2, 9, 250)), 10)
