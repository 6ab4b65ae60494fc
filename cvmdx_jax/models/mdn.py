"""A mixture density network: K Gaussian trajectory modes and their probabilities (beyond
the paper; the CS-LSTM / MTP family of probabilistic regressors).

The probabilistic learned baseline beside the multiple-choice MLP
(`cvmdx_jax.models.multiple_choice`): the same inputs (token q, log(1 + delta), the
ego-motion + neighbour features), the same trunk and the same K mode means, rolled out
with the VMM from the residual to the ego's extrapolated controls, so that every mean is
a drivable trajectory starting with the ego's speed and heading. One more head gives
each mode a per-step axis-aligned standard deviation of the position in the scenario
frame, sigma = `std_floor_m` + exp(s) with s the head's output: the floor keeps the
density finite where a mode fits the truth to the millimetre (the first steps after
t0); the head's kernel starts small, so every sigma starts near floor + 1 m.

The distribution of the future (125, 2) is
  p(y) = sum_k pi_k prod_{t, d} N(y_td; mu_ktd, sigma_ktd^2),   pi = softmax(logits),
and `log_likelihood` is log p(y) in nats (`cvmdx_jax.train.mdn` minimises its negative).
"""

import math

import jax
import jax.numpy as jnp
from flax import nnx

from cvmdx_jax import constants
from cvmdx_jax.config.mdn import MixtureDensityConfig
from cvmdx_jax.models import functional
from cvmdx_jax.models import multiple_choice as mc

_LOG_2PI = math.log(2.0 * math.pi)


class MixtureDensityMLP(mc.MultipleChoiceMLP):
  """(q, delta, ego) -> (normalised residual controls (B, K, 125, 2), log-std head
  s (B, K, 125, 2), logits (B, K))."""

  def __init__(self, config: MixtureDensityConfig, *, rngs: nnx.Rngs):
    super().__init__(config, rngs=rngs)
    out_init = nnx.initializers.variance_scaling(mc.OUTPUT_INIT_SCALE, "fan_in", "normal")
    self.log_std = nnx.Linear(
        config.hidden[-1],
        config.num_hypotheses * constants.T_PRED * 2,
        kernel_init=out_init,
        rngs=rngs,
    )

  def __call__(self, q, delta, ego):
    h = self.features(q, delta, ego)
    controls, logits = self.heads(h)
    return controls, self.log_std(h).reshape(controls.shape), logits


def init(config: MixtureDensityConfig, key: jax.Array) -> tuple[nnx.GraphDef, dict]:
  """(graphdef, params), params a pure dict."""
  return functional.init(lambda rngs: MixtureDensityMLP(config, rngs=rngs), key)


def make_graphdef(config: MixtureDensityConfig) -> nnx.GraphDef:
  """The graph definition alone (no parameters are allocated)."""
  return functional.make_graphdef(MixtureDensityMLP, config)


def abstract_params(config: MixtureDensityConfig) -> dict:
  """The parameters' shapes and dtypes (`jax.ShapeDtypeStruct`s; nothing is allocated)."""
  return functional.abstract_params(MixtureDensityMLP, config)


def mixture(graphdef, params, config: MixtureDensityConfig, q, delta, ego, v0, psi0):
  """The mixture of B scenarios.

  Args:
    graphdef, params: the model (`init`).
    config: its config.
    q: (B,) int tokens; delta: (B,) uncertainty; ego: (B, F) ego-motion features;
    v0, psi0: (B,) speed m/s and heading rad at t0.

  Returns:
    (means (B, K, 125, 2) m, stds (B, K, 125, 2) m, logits (B, K)).
  """
  controls, log_std, logits = nnx.merge(graphdef, params)(q, delta, ego)
  means = mc.rollout(config, controls, ego, v0, psi0)
  return means, config.std_floor_m + jnp.exp(log_std), logits


def mode_log_densities(means, stds, future):
  """log N(future; mean_k, diag(std_k^2)) over the whole trajectory, nats.

  Args:
    means, stds: (B, K, T, 2) m; future: (B, T, 2) m.

  Returns:
    (B, K): the sum over steps and coordinates of the per-coordinate log densities.
  """
  z = (future[:, None] - means) / stds
  return -jnp.sum(0.5 * z**2 + jnp.log(stds) + 0.5 * _LOG_2PI, axis=(-2, -1))


def log_likelihood(means, stds, logits, future):
  """log p(future) (B,) nats of the mixture with weights softmax(logits (B, K)); see
  `mode_log_densities`."""
  log_weights = jax.nn.log_softmax(logits, axis=-1)
  return jax.nn.logsumexp(log_weights + mode_log_densities(means, stds, future), axis=-1)
