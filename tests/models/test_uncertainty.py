"""Per-entry Gaussians and Mahalanobis delta against numpy/scipy references."""

import jax
import numpy as np
import pytest
import scipy.spatial.distance

from cvmdx_jax.models import uncertainty


def _fixture(seed=0):
  rng = np.random.default_rng(seed)
  codebook = rng.normal(0, 3, (4, 3)).astype(np.float32)
  # entry 0: 200 members, 1: 2 members (< D = 3), 2: 1 member, 3: none.
  idx = np.concatenate([np.zeros(200, int), [1, 1, 2]]).astype(np.int32)
  scale = np.array([1.0, 0.3, 2.0], np.float32)
  z = (codebook[idx] + rng.normal(0, 1, (idx.size, 3)) * scale).astype(np.float32)
  return z, idx, codebook


def test_covariances_match_shrinkage_closed_form():
  z, idx, codebook = _fixture()
  k, ridge = 5.0, 1e-3
  g = jax.jit(uncertainty.fit_gaussians, static_argnums=(3, 4))(z, idx, codebook, k, ridge)
  d = (z - codebook[idx]).astype(np.float64)
  pooled = d.T @ d / len(z)
  pooled += (ridge * np.mean(np.diag(pooled)) + 1e-6) * np.eye(3)
  for q in range(4):
    members = d[idx == q]
    n = len(members)
    own = members.T @ members / max(n, 1)
    expected = n / (n + k) * own + k / (n + k) * pooled
    np.testing.assert_allclose(g.cov[q], expected, rtol=2e-4, atol=1e-6)
  np.testing.assert_array_equal(g.count, [200, 2, 1, 0])
  np.testing.assert_allclose(g.mean, codebook)


def test_few_member_entries_stay_invertible():
  z, idx, codebook = _fixture(1)
  g = uncertainty.fit_gaussians(z, idx, codebook, shrinkage=1.0, ridge=0.0)
  for q in (1, 2, 3):  # fewer members than the 3 latent dimensions
    assert np.linalg.eigvalsh(np.asarray(g.cov[q], np.float64)).min() > 0
    np.testing.assert_allclose(
        np.asarray(g.precision[q]) @ np.asarray(g.cov[q]), np.eye(3), atol=1e-3
    )
  # even with a single latent overall (pooled covariance of rank <= 1) Sigma is invertible
  one = uncertainty.fit_gaussians(z[:1], idx[:1], codebook)
  assert np.all(np.isfinite(one.precision))
  assert np.linalg.eigvalsh(np.asarray(one.cov[0], np.float64)).min() > 0


def test_mahalanobis_equals_scipy():
  z, idx, codebook = _fixture(2)
  g = uncertainty.fit_gaussians(z, idx, codebook)
  rng = np.random.default_rng(3)
  probe = rng.normal(0, 2, (10, 3)).astype(np.float32)
  probe_idx = rng.integers(0, 4, 10).astype(np.int32)
  delta = jax.jit(uncertainty.mahalanobis)(probe, probe_idx, g)
  for i in range(10):
    cov = np.asarray(g.cov[probe_idx[i]], np.float64)
    ref = scipy.spatial.distance.mahalanobis(probe[i], codebook[probe_idx[i]], np.linalg.inv(cov))
    np.testing.assert_allclose(delta[i], ref, rtol=1e-4)


def test_bad_shrinkage_is_refused():
  z, idx, codebook = _fixture()
  for kwargs in ({"shrinkage": 0.0}, {"ridge": -1.0}):
    with pytest.raises(ValueError, match="shrinkage"):
      uncertainty.fit_gaussians(z, idx, codebook, **kwargs)
