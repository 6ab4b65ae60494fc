"""Motion hypotheses from N sampled trajectories per scenario.

Two methods (`HypothesisConfig.method`). "bic", the paper's (cVMDx Sec. III-C), per
scenario: scale x and y, flatten each trajectory, PCA to r dims, fit
full-covariance GMMs with C = 1..c_max by EM, keep the C of lowest BIC, assign
every sample to its most likely component, and report each hypothesis as the
mean of its samples (in metres) with probability p(c) = share of samples.
Everything is one jittable function, `vmap`-ped over scenarios and over C;
nothing per scenario runs in Python and scikit-learn is not used.
"kmeans" (beyond the paper; `kmeans`): always c_max hypotheses, the means of a k-means
partition of the trajectories in metres, built to cover the true future (minFDE_K) where
BIC keeps a single mode in most highway scenarios; p(c) = share of samples as well.

`HypothesisConfig.prob_temperature` t (beyond the paper; 1 keeps the share): p(c) =
share^t / sum_c' share^t (`temper`). A share is how often the model samples a mode, not how
often its mean is the one closest to the truth; with t < 1 chosen on val by the log loss of
the closest hypothesis (`evaluation.prob_calibration`), p(c) is that probability, calibrated.

Hypothesis slots are ordered by probability, descending (ties keep the lower
component index), so slot 0 is the most likely hypothesis and slots
>= num_modes are empty (probability 0, mean 0).
"""

import dataclasses

import jax
import jax.numpy as jnp

from cvmdx_jax import constants
from cvmdx_jax.config.sampling import HypothesisConfig
from cvmdx_jax.errors import UserError
from cvmdx_jax.multimodal import gmm, kmeans, pca, scaling


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Hypotheses:
  """Hypotheses of B scenarios with c_max slots each, ordered by probability.

  Attributes:
    num_modes: (B,) int, number of non-empty hypotheses (slots 0..num_modes-1).
      Equals num_components unless a fitted component attracts no sample.
    num_components: (B,) int, the C in 1..c_max of lowest BIC; c_max for "kmeans".
    labels: (B, N) int in [0, num_modes), the hypothesis of each sample.
    means: (B, c_max, T, 2) mean trajectory of each hypothesis's samples, in
      the input's metres; 0 for empty slots.
    probs: (B, c_max) share of samples per hypothesis (tempered: `temper`), descending,
      0 for empty slots, summing to 1.
    bic: (B, c_max) BIC of the fit with C = 1..c_max (+inf if non-finite); NaN for
      "kmeans", which fits no mixture.
  """

  num_modes: jax.Array
  num_components: jax.Array
  labels: jax.Array
  means: jax.Array
  probs: jax.Array
  bic: jax.Array


def embed(trajectories: jax.Array, config: HypothesisConfig) -> jax.Array:
  """Scaled, flattened and PCA-projected samples: the points the GMM sees.

  Args:
    trajectories: (B, N, T, 2) positions in metres.
    config: the `HypothesisConfig`.

  Returns:
    (B, N, pca_dim) principal-component scores.
  """
  scaled = scaling.scale(trajectories, config.scaling, config.x_scale, config.y_scale)
  return pca.project(scaled.reshape(scaled.shape[:2] + (-1,)), config.pca_dim)


def _group(component, trajectories, num_slots: int):
  """Slots ordered by size from the (N,) group of each sample: (num_modes, labels,
  means (num_slots, T, 2), probs (num_slots,)), see `Hypotheses`."""
  counts = jnp.sum(jax.nn.one_hot(component, num_slots, dtype=jnp.int32), axis=0)
  order = jnp.argsort(-counts, stable=True)  # slot -> component
  rank = jnp.argsort(order)  # component -> slot
  labels = rank[component]
  counts = counts[order]
  one_hot = jax.nn.one_hot(labels, num_slots, dtype=trajectories.dtype)  # (N, num_slots)
  sums = jnp.einsum("nk,ntd->ktd", one_hot, trajectories, precision=constants.EXACT_MATMUL)
  means = sums / jnp.maximum(counts, 1).astype(trajectories.dtype)[:, None, None]
  return (
      jnp.sum(counts > 0).astype(jnp.int32),
      labels.astype(jnp.int32),
      means,
      counts.astype(trajectories.dtype) / component.shape[0],
  )


def _select_one(points, trajectories, config: HypothesisConfig):
  """BIC hypotheses of one scenario from its (N, r) points and (N, T, 2) samples."""
  num_points, dim = points.shape
  c_max = config.c_max
  candidates = jnp.arange(1, c_max + 1)
  fits = jax.vmap(lambda c: gmm.fit(points, c, c_max, config.reg_covar, config.em_iters))(
      candidates
  )
  bic = gmm.bic(fits.log_likelihood, candidates, dim, num_points)
  best = jnp.argmin(bic)
  component = jnp.argmax(fits.responsibilities[best], axis=-1)  # (N,)
  num_modes, labels, means, probs = _group(component, trajectories, c_max)
  return Hypotheses(
      num_modes=num_modes,
      num_components=(best + 1).astype(jnp.int32),
      labels=labels,
      means=means,
      probs=probs,
      bic=bic,
  )


def _kmeans_one(trajectories, config: HypothesisConfig):
  """k-means hypotheses of one scenario from its (N, T, 2) samples."""
  points = kmeans.features(trajectories, config.endpoint_weight)
  _, component = kmeans.fit(points, config.c_max, config.kmeans_iters)
  num_modes, labels, means, probs = _group(component, trajectories, config.c_max)
  return Hypotheses(
      num_modes=num_modes,
      num_components=jnp.int32(config.c_max),
      labels=labels,
      means=means,
      probs=probs,
      bic=jnp.full((config.c_max,), jnp.nan, trajectories.dtype),
  )


def temper(probs: jax.Array, temperature: float) -> jax.Array:
  """probs (..., K) raised to `temperature` and renormalised over the non-empty (> 0)
  entries; empty entries stay 0, the order is kept. `temperature` 1 returns `probs`."""
  if temperature == 1.0:
    return probs
  present = probs > 0
  powered = jnp.where(present, jnp.power(jnp.where(present, probs, 1.0), temperature), 0.0)
  return powered / jnp.sum(powered, axis=-1, keepdims=True)


def _tempered(hyp: Hypotheses, config: HypothesisConfig) -> Hypotheses:
  return dataclasses.replace(hyp, probs=temper(hyp.probs, config.prob_temperature))


def fit_hypotheses(
    trajectories: jax.Array, c_max: int | None = None, config: HypothesisConfig | None = None
) -> Hypotheses:
  """Motion hypotheses of sampled trajectories, batched over scenarios.

  Plain jittable code: jit it at the caller's boundary, e.g.
  `jax.jit(fit_hypotheses, static_argnames=("c_max", "config"))`.

  Args:
    trajectories: (B, N, T, 2) sampled positions [x, y] in metres.
    c_max: largest number of hypotheses; defaults to `config.c_max` (3).
    config: `HypothesisConfig`; default `HypothesisConfig()`.

  Returns:
    `Hypotheses` with slots ordered by probability, descending.

  Raises:
    ValueError: wrong shape, non-float input, or `c_max` that contradicts
      `config.c_max` or exceeds N with method "bic" ("kmeans" leaves the surplus
      slots empty).
  """
  if config is None:
    config = HypothesisConfig() if c_max is None else HypothesisConfig(c_max=c_max)
  elif c_max is not None and c_max != config.c_max:
    raise UserError(f"fit_hypotheses: c_max={c_max} contradicts config.c_max={config.c_max}")
  trajectories = jnp.asarray(trajectories)
  if trajectories.ndim != 4 or trajectories.shape[-1] != 2:
    raise UserError(f"fit_hypotheses: trajectories must be (B, N, T, 2), got {trajectories.shape}")
  if not jnp.issubdtype(trajectories.dtype, jnp.floating):
    raise UserError(f"fit_hypotheses: trajectories must be floating, got {trajectories.dtype}")
  if config.method == "kmeans":
    return _tempered(jax.vmap(lambda t: _kmeans_one(t, config))(trajectories), config)
  if config.c_max > trajectories.shape[1]:
    raise UserError(
        f"fit_hypotheses: c_max={config.c_max} exceeds N={trajectories.shape[1]} samples"
    )
  points = embed(trajectories, config)
  return _tempered(jax.vmap(lambda p, t: _select_one(p, t, config))(points, trajectories), config)
