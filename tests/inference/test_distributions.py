"""The two distribution forms: densities against scipy, sampling moments, constructors."""

import jax
import jax.numpy as jnp
import numpy as np
from scipy import stats

from cvmdx_jax.inference import distributions


def _mixture(seed=0, m=3, k=2, t=4):
  rng = np.random.default_rng(seed)
  w = rng.uniform(0.2, 1.0, (m, k))
  return distributions.GaussianMixture(
      means=jnp.asarray(rng.normal(size=(m, k, t, 2))),
      stds=jnp.asarray(rng.uniform(0.3, 1.5, (m, k, t, 2))),
      weights=jnp.asarray(w / w.sum(1, keepdims=True)),
  )


def test_log_density_matches_scipy():
  mix = _mixture()
  y = np.random.default_rng(1).normal(size=(3, 4, 2))
  got = np.asarray(mix.log_density(jnp.asarray(y)))
  means, stds, w = map(np.asarray, (mix.means, mix.stds, mix.weights))
  for i in range(3):
    for t in range(4):
      p = sum(
          w[i, k]
          * stats.multivariate_normal.pdf(y[i, t], means[i, k, t], np.diag(stds[i, k, t] ** 2))
          for k in range(2)
      )
      np.testing.assert_allclose(got[i, t], np.log(p), rtol=1e-5)


def test_sample_moments_match_mixture():
  mix = _mixture(m=2, t=3)
  s = mix.sample(jax.random.key(0), 20000)
  assert s.points.shape == (2, 20000, 3, 2)
  np.testing.assert_allclose(np.asarray(s.weights.sum(1)), 1.0, rtol=1e-6)
  np.testing.assert_allclose(np.asarray(s.points.mean(1)), np.asarray(mix.mean()), atol=0.05)


def test_point_mass_and_uniform():
  traj = jnp.arange(12.0).reshape(2, 3, 2)
  pm = distributions.WeightedSamples.point_mass(traj)
  assert pm.points.shape == (2, 1, 3, 2)
  np.testing.assert_array_equal(np.asarray(pm.mean()), np.asarray(traj))
  u = distributions.WeightedSamples.uniform(jnp.zeros((2, 4, 3, 2)))
  np.testing.assert_allclose(np.asarray(u.weights), 0.25)
