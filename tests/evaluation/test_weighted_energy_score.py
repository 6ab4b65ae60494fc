"""The weighted energy score against scoringrules (an independent implementation)."""

import math

import jax.numpy as jnp
import numpy as np
import scoringrules as sr

from cvmdx_jax.evaluation import probabilistic


def _case(seed, m=4, n=6, t=5):
  rng = np.random.default_rng(seed)
  return rng.normal(size=(m, n, t, 2)), rng.normal(size=(m, t, 2))


def _flat(a, t):
  return a.reshape(a.shape[:-2] + (-1,)) / math.sqrt(t)  # d = |a - b|_2 / sqrt(T)


def test_uniform_fair_matches_scoringrules():
  x, y = _case(0)
  w = np.full(x.shape[:2], 1.0 / x.shape[1])
  got = probabilistic.weighted_energy_score(
      jnp.asarray(x), jnp.asarray(w), jnp.asarray(y), fair=True
  )
  want = sr.es_ensemble(_flat(y, 5), _flat(x, 5), estimator="fair", backend="numpy")
  np.testing.assert_allclose(np.asarray(got), want, rtol=1e-5)
  np.testing.assert_allclose(
      np.asarray(probabilistic.energy_score(jnp.asarray(x), jnp.asarray(y))), want, rtol=1e-5
  )


def test_weighted_exact_equals_repeated_points():
  """Weights (1/2, 1/4, 1/4) are the ensemble (a, a, b, c) under the all-pairs score."""
  x, y = _case(1, n=3)
  w = np.tile([0.5, 0.25, 0.25], (x.shape[0], 1))
  got = probabilistic.weighted_energy_score(
      jnp.asarray(x), jnp.asarray(w), jnp.asarray(y), fair=False
  )
  repeated = x[:, [0, 0, 1, 2]]
  want = sr.es_ensemble(_flat(y, 5), _flat(repeated, 5), estimator="nrg", backend="numpy")
  np.testing.assert_allclose(np.asarray(got), want, rtol=1e-5)
  want_w = sr.es_ensemble(_flat(y, 5), _flat(x, 5), ens_w=w, estimator="nrg", backend="numpy")
  np.testing.assert_allclose(np.asarray(got), want_w, rtol=1e-5)


def test_one_dimension_is_the_crps():
  """With T = 1 and the lateral coordinate 0 the energy score is the CRPS."""
  rng = np.random.default_rng(2)
  xs, ys = rng.normal(size=(5, 8)), rng.normal(size=5)
  pad = lambda a: np.stack([a, np.zeros_like(a)], -1)[..., None, :]
  got = probabilistic.energy_score(jnp.asarray(pad(xs)), jnp.asarray(pad(ys)))
  want = sr.crps_ensemble(ys, xs, estimator="fair", backend="numpy")
  np.testing.assert_allclose(np.asarray(got), want, rtol=1e-5)


def test_point_mass_is_the_distance_and_fair_needs_two_points():
  y = np.zeros((1, 4, 2))
  x = np.full((1, 1, 4, 2), [3.0, 4.0])
  for fair in (True, False):
    got = probabilistic.weighted_energy_score(
        jnp.asarray(x), jnp.ones((1, 1)), jnp.asarray(y), fair=fair
    )
    np.testing.assert_allclose(np.asarray(got), [5.0], rtol=1e-6)
