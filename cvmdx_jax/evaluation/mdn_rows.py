"""The mixture density network in a report: its rows and per-scenario errors.

Rows (`METHODS`): the mixture's mean trajectory (`mdn_mean`: ADE, FDE, ... as every
single trajectory, plus `energy_score` (m) of `ES_SAMPLES` trajectories drawn from the
mixture with the fair estimator, and `nll_final` (nats), its exact density of the true
5 s position) and its K modes with their weights (`mdn_best_of_k`: minADE_K, minFDE_K,
Brier-minFDE, `energy_score` of the modes' means as a discrete distribution, ... as
cVMDx's hypotheses).
"""

import jax
import jax.numpy as jnp

from cvmdx_jax.evaluation import probabilistic, scoring
from cvmdx_jax.inference.distributions import GaussianMixture

METHODS = ("mdn_mean", "mdn_best_of_k")
ES_SAMPLES = 64
ES_SEED = 0  # the draw of the energy score's samples


def errors(mixture: GaussianMixture, gt, labels) -> dict:
  """{method: {metric: (M,)}} of the rows `METHODS`; gt (M, T, 2), labels (M,)."""
  gt = jnp.asarray(gt)
  means, weights = jnp.asarray(mixture.means), jnp.asarray(mixture.weights)
  used = jnp.maximum(weights, jnp.finfo(weights.dtype).tiny)  # every mode is a hypothesis
  mean, modes_es = _mixture_scores(means, jnp.asarray(mixture.stds), weights, gt)
  best = {**scoring.best_of_k_errors(means, used, gt, labels), "energy_score": modes_es}
  return {"mdn_mean": mean, "mdn_best_of_k": best}


@jax.jit
def _mixture_scores(means, stds, weights, gt) -> tuple[dict, jax.Array]:
  """(the mean row's errors, the modes' energy score as a discrete distribution)."""
  mixture = GaussianMixture(means, stds, weights)
  sampled = mixture.sample(jax.random.key(ES_SEED), ES_SAMPLES)
  mean = {
      **scoring.single_trajectory_errors(mixture.mean(), gt),
      "energy_score": probabilistic.weighted_energy_score(
          sampled.points, sampled.weights, gt, fair=True
      ),
      "nll_final": -mixture.log_density(gt)[:, -1],
  }
  return mean, probabilistic.weighted_energy_score(means, weights, gt, fair=False)
