"""EM for a fixed C, log-likelihood and BIC, against closed forms and scikit-learn."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import threadpoolctl
from scipy import stats
from sklearn import mixture

from cvmdx_jax.multimodal import gmm
from tests.multimodal import oracle

REG = 1e-2


def _fit(points, num_components, max_components=3, iters=30, reg=REG):
  fit = jax.jit(gmm.fit, static_argnums=(2, 3, 4))
  return fit(jnp.asarray(points, jnp.float32), num_components, max_components, reg, iters)


def test_single_component_is_closed_form_gaussian_mle():
  rng = np.random.default_rng(0)
  points = rng.normal(size=(9, 2)) @ np.array([[1.0, 0.0], [0.8, 0.3]])
  result = _fit(points, 1)
  cov = np.cov(points.T, bias=True) + REG * np.eye(2)
  want = stats.multivariate_normal(points.mean(axis=0), cov).logpdf(points).sum()
  np.testing.assert_allclose(float(result.log_likelihood), want, rtol=1e-5)
  np.testing.assert_allclose(np.asarray(result.mixture.weights), [1.0, 0.0, 0.0])


def test_parameter_count_and_bic_match_sklearn():
  assert [gmm.num_parameters(c, 2) for c in (1, 2, 3)] == [5, 11, 17]  # 6C - 1
  rng = np.random.default_rng(1)
  points = np.concatenate([rng.normal(size=(5, 3)), rng.normal(size=(4, 3)) + 6.0])
  model = mixture.GaussianMixture(2, covariance_type="full", reg_covar=REG).fit(points)
  log_like = model.score(points) * len(points)
  np.testing.assert_allclose(gmm.bic(log_like, 2, 3, 9), model.bic(points), rtol=1e-12)


def test_farthest_point_seeds_hand_worked():
  # Mean 3.25: farthest is 10 (index 3); then 0 (index 0); then min distance to
  # {10, 0} is 1 for point 1 and 2 for point 2, so index 2.
  points = jnp.asarray([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [10.0, 0.0]])
  np.testing.assert_array_equal(np.asarray(gmm.farthest_point_seeds(points, 3)), [3, 0, 2])
  resp = gmm.initial_responsibilities(points, 2, 3)
  np.testing.assert_array_equal(np.asarray(resp), [[0, 1, 0], [0, 1, 0], [0, 1, 0], [1, 0, 0]])


@pytest.mark.filterwarnings("ignore::sklearn.exceptions.ConvergenceWarning")
def test_em_matches_sklearn_from_same_start():
  rng = np.random.default_rng(2)
  sets = np.concatenate(
      [rng.normal(size=(20, 4, 2)) * 0.3, rng.normal(size=(20, 5, 2)) + 1.0], axis=1
  )
  for c in (2, 3):
    fit = jax.jit(jax.vmap(lambda p, c=c: gmm.fit(p, c, 3, REG, 30)))
    result = fit(jnp.asarray(sets, jnp.float32))
    with threadpoolctl.threadpool_limits(1):
      for i, points in enumerate(sets):
        init = oracle.initial_parameters(points, oracle.farthest_point_labels(points, c), c, REG)
        model = mixture.GaussianMixture(
            c, covariance_type="full", reg_covar=REG, tol=0.0, max_iter=30, **init
        ).fit(points)
        np.testing.assert_allclose(
            float(result.log_likelihood[i]),
            model.score(points) * 9,
            rtol=1e-4,
            atol=1e-3,
            err_msg=f"set {i}, C={c}",
        )
        np.testing.assert_allclose(
            np.asarray(result.mixture.weights[i, :c]), model.weights_, atol=1e-4
        )


def test_degenerate_sets_stay_finite():
  identical = np.ones((9, 2))
  two_points = np.repeat([[0.0, 0.0], [1.0, 1.0]], [5, 4], axis=0)  # rank-0 clusters
  for points in (identical, two_points):
    for c in (1, 2, 3):
      result = _fit(points, c)
      assert np.isfinite(float(result.log_likelihood))
      np.testing.assert_allclose(float(jnp.sum(result.mixture.weights)), 1.0, rtol=1e-6)
      np.testing.assert_allclose(np.asarray(result.responsibilities.sum(axis=1)), 1.0, rtol=1e-5)
      assert np.all(np.asarray(result.responsibilities[:, c:]) == 0.0)
  # All points identical: every component is the floor Gaussian at that point.
  want = 9 * stats.multivariate_normal([1.0, 1.0], REG * np.eye(2)).logpdf([1.0, 1.0])
  np.testing.assert_allclose(float(_fit(identical, 3).log_likelihood), want, rtol=1e-4)
