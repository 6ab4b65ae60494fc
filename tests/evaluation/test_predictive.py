"""The models of the quality benchmark built from a prediction (`evaluation.predictive`)."""

import jax
import jax.numpy as jnp
import numpy as np

from cvmdx_jax import constants
from cvmdx_jax.evaluation import model_scores, predictive
from cvmdx_jax.inference.distributions import GaussianMixture


def test_mdn_modes_are_its_means_with_their_weights_scored_as_a_discrete_set():
  """Two modes 2 m apart laterally, weights 0.25 / 0.75, truth on the second: the exact
  energy score of the two-point set is sum_k w_k d(x_k, y) - w_1 w_2 d(x_1, x_2)
  = 0.25 * 2 - 0.25 * 0.75 * 2 = 0.125 m (d the rms displacement over the steps)."""
  t = constants.T_PRED
  means = np.zeros((1, 2, t, 2), np.float32)
  means[0, 1, :, 1] = 2.0
  mixture = GaussianMixture(
      jnp.asarray(means), jnp.full((1, 2, t, 2), 0.5), jnp.asarray([[0.25, 0.75]])
  )
  full, modes = predictive.mdn_models(mixture)
  assert (full.name, modes.name) == ("mdn", "mdn_modes")
  np.testing.assert_array_equal(np.asarray(modes.distribution.points), means)
  np.testing.assert_allclose(np.asarray(modes.distribution.weights), [[0.25, 0.75]])
  assert not modes.fair and modes.k_set is modes.distribution
  gt = means[:, 1]
  scores = model_scores.scenario_scores(modes, gt, [(0.0, 0.1, 0.1)] * 5, jax.random.key(0))
  np.testing.assert_allclose(scores["energy_score"], [0.125], rtol=1e-5)
  np.testing.assert_allclose(scores["min_fde"], [0.0], atol=1e-6)
  # the truth is on the second mode: Brier-minFDE charges (1 - 0.75)^2, the log loss -log 0.75
  np.testing.assert_allclose(scores["brier_min_fde"], [0.0625], atol=1e-6)
  np.testing.assert_allclose(scores["closest_log_loss"], [-np.log(0.75)], rtol=1e-6)
