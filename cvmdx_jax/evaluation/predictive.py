"""Every model's prediction on a split as a `model_scores.Model`, scored the same way.

cvmdx_samples     cVMDx's N samples (uniform, fair); K-set: its hypotheses; density: a
                  Gaussian per hypothesis cluster of the samples (labels)
cvmdx_hypotheses  cVMDx's K hypotheses with their probabilities (what users get)
mlp_heads         the WTA MLP's heads with their p (`inference.bundles.LearnedBaseline`)
mdn               the mixture density network (exact density; sampled for the energy
                  score); K-set: its mode means with their weights
mdn_modes         the MDN's mode means with their weights (its heads: what a user of it
                  gets as hypotheses, beside cVMDx's)
cv, ca            constant velocity, constant acceleration + yaw rate (point masses)
"""

import jax.numpy as jnp
import numpy as np

from cvmdx_jax.evaluation import baselines
from cvmdx_jax.evaluation.model_scores import Model
from cvmdx_jax.inference.distributions import GaussianMixture, WeightedSamples

TITLES = {
    "cvmdx_samples": "cVMDx, N samples",
    "cvmdx_hypotheses": "cVMDx, K hypotheses + p(c)",
    "mlp_heads": "MLP, 3 heads (WTA) + p",
    "mdn": "MDN, 3 Gaussian modes",
    "mdn_modes": "MDN, 3 mode means + weights",
    "cv": "Constant velocity",
    "ca": "Constant acceleration + yaw rate",
}


def _k_set(points, probs) -> WeightedSamples:
  """Heads / hypotheses with probabilities renormalised (an underflowed p stays a head)."""
  probs = np.maximum(np.asarray(probs, np.float64), np.finfo(np.float32).tiny)
  probs = probs / probs.sum(axis=1, keepdims=True)
  return WeightedSamples(jnp.asarray(points, jnp.float32), jnp.asarray(probs, jnp.float32))


def cvmdx_models(output) -> list:
  """The two cVMDx rows of a `PredictorOutput`."""
  hyp = output.hypotheses
  probs = np.asarray(hyp.probs, np.float32)
  hypotheses = WeightedSamples(
      jnp.asarray(hyp.means, jnp.float32), jnp.asarray(probs / probs.sum(axis=1, keepdims=True))
  )
  samples = WeightedSamples.uniform(jnp.asarray(output.prediction.trajectories, jnp.float32))
  return [
      Model("cvmdx_samples", samples, fair=True, k_set=hypotheses, labels=np.asarray(hyp.labels)),
      Model("cvmdx_hypotheses", hypotheses, k_set=hypotheses),
  ]


def physics_models(scenarios) -> list:
  """Constant velocity and constant acceleration + yaw rate as point masses."""
  return [
      Model("cv", WeightedSamples.point_mass(baselines.constant_velocity(scenarios.xi))),
      Model(
          "ca", WeightedSamples.point_mass(baselines.constant_acceleration_yaw_rate(scenarios.xi))
      ),
  ]


def mlp_model(baseline, output, scenarios) -> Model:
  """The WTA MLP's heads with their p, on the evaluated tokeniser's q and delta."""
  trajectories, probs = baseline(
      output.q, output.delta, scenarios.xi, scenarios.mask, scenarios.v0, scenarios.psi0
  )
  heads = _k_set(trajectories, probs)
  return Model("mlp_heads", heads, k_set=heads)


def mdn_models(mixture: GaussianMixture) -> list:
  """The MDN's mixture and its mode means with their weights (a K-set of both)."""
  modes = _k_set(mixture.means, mixture.weights)
  return [Model("mdn", mixture, k_set=modes), Model("mdn_modes", modes, k_set=modes)]
