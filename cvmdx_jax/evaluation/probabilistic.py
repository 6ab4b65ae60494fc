"""Probabilistic scores of sampled trajectories and of their hypotheses (pure jnp).

- `energy_score`: ES = E d(X, y) - 1/2 E d(X, X') of the N samples X against the true
  trajectory y (Gneiting and Raftery 2007), a strictly proper score in metres: lower
  is better, and in expectation no distribution scores lower than the true one. The
  distance d is the root-mean-square displacement over the T steps,
  d(a, b) = sqrt(mean_t |a_t - b_t|^2) = |a - b|_2 / sqrt(T), the Euclidean norm of the
  flattened trajectory rescaled to metres per step. The Euclidean norm of the whole
  trajectory keeps the score strictly proper for the joint distribution of the
  trajectory; a mean of per-step norms (the ADE distance) is a sum of per-step energy
  scores, proper only for the per-step marginals. E d(X, X') uses the N (N - 1) pairs
  i != j (the unbiased "fair" estimate), so a single sample scores E d(X, y).
  `weighted_energy_score` generalises it to weights (`distributions.WeightedSamples`).
- `mixture_nll`, `hypothesis_covariances`: negative log-likelihood (nats) of the true
  5 s position under the hypotheses as a Gaussian mixture: weights p(c), means the
  hypotheses' 5 s positions, covariances the (maximum-likelihood) covariance of their
  members' 5 s positions plus `COVARIANCE_FLOOR_M2` I (0.1 m^2 per axis, ~0.3 m: the
  scale of a lane marking; defines singleton hypotheses and bounds the density).
- `reliability`, `expected_calibration_error`: calibration of hypothesis probabilities
  as confidence that "this hypothesis is the closest to the truth" (smallest final
  error, the one minFDE_K picks), over `NUM_BINS` equal-width bins of p.

Every public function is jitted (one program per input shape instead of an XLA program for
each operation called eagerly: a report compiled ~280 of those per split).
"""

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp

from cvmdx_jax import constants

COVARIANCE_FLOOR_M2 = 0.1  # added to each axis of every hypothesis covariance, m^2
NUM_BINS = 10  # calibration bins of equal width over [0, 1]


def _rms_displacement_sq(a, b):
  return jnp.mean(jnp.sum((a - b) ** 2, axis=-1), axis=-1)


@jax.jit
def energy_score(samples, gt):
  """Energy score (m) of samples (..., N, T, 2) against gt (..., T, 2) -> (...,)."""
  n = samples.shape[-3]
  weights = jnp.full(samples.shape[:-2], 1.0 / n, samples.dtype)
  return weighted_energy_score(samples, weights, gt, fair=True)


@functools.partial(jax.jit, static_argnames="fair")
def weighted_energy_score(points, weights, gt, fair: bool):
  """Energy score (m) of a weighted set of trajectories against gt.

  ES = sum_i w_i d(x_i, y) - 1/2 S with S = sum_{i != j} w_i w_j d(x_i, x_j), divided by
  1 - sum_i w_i^2 when `fair` (samples drawn from a model: with w = 1 / N the unbiased
  N (N - 1) pair mean) and not divided otherwise (the exact score of the discrete
  distribution: heads with their p, hypotheses, a point mass). A single point (or one
  weight of 1) scores d(x, y) either way.

  points (..., N, T, 2), weights (..., N) summing to 1, gt (..., T, 2) -> (...,).
  """
  to_truth = jnp.sum(weights * jnp.sqrt(_rms_displacement_sq(points, gt[..., None, :, :])), axis=-1)
  if points.shape[-3] == 1:
    return to_truth
  # pairwise distances from the Gram matrix of the centred points (B x N x N memory)
  centred = points - jnp.mean(points, axis=-3, keepdims=True)
  flat = centred.reshape(centred.shape[:-2] + (-1,)) / math.sqrt(points.shape[-2])
  sq_norm = jnp.sum(flat**2, axis=-1)
  gram = jnp.einsum("...id,...jd->...ij", flat, flat, precision=constants.EXACT_MATMUL)
  sq = jnp.maximum(sq_norm[..., :, None] + sq_norm[..., None, :] - 2.0 * gram, 0.0)
  n = points.shape[-3]
  pair_w = weights[..., :, None] * weights[..., None, :] * (1.0 - jnp.eye(n, dtype=points.dtype))
  spread = jnp.sum(jnp.sqrt(sq) * pair_w, axis=(-2, -1))
  if fair:
    norm = 1.0 - jnp.sum(weights**2, axis=-1)
    spread = jnp.where(norm > 1e-9, spread / jnp.where(norm > 1e-9, norm, 1.0), 0.0)
  return to_truth - 0.5 * spread


@functools.partial(jax.jit, static_argnames="num_slots")
def hypothesis_covariances(points, labels, num_slots: int, floor: float = COVARIANCE_FLOOR_M2):
  """Covariance of each hypothesis's members plus floor * I.

  Args:
    points: (..., N, 2) member positions (e.g. the samples' 5 s positions), m.
    labels: (..., N) int hypothesis of each member.
    num_slots: static K.
    floor: m^2 added to each diagonal entry.

  Returns:
    means (..., K, 2) and covariances (..., K, 2, 2) (floor * I for empty slots).
  """
  one_hot = jax.nn.one_hot(labels, num_slots, dtype=points.dtype)  # (..., N, K)
  counts = jnp.maximum(jnp.sum(one_hot, axis=-2), 1.0)  # (..., K)
  means = (
      jnp.einsum("...nk,...nd->...kd", one_hot, points, precision=constants.EXACT_MATMUL)
      / counts[..., None]
  )
  dev = points[..., None, :, :] - means[..., :, None, :]  # (..., K, N, 2)
  weighted = dev * jnp.swapaxes(one_hot, -1, -2)[..., None]
  cov = (
      jnp.einsum("...kni,...knj->...kij", weighted, dev, precision=constants.EXACT_MATMUL)
      / counts[..., None, None]
  )
  return means, cov + floor * jnp.eye(2, dtype=points.dtype)


@jax.jit
def mixture_nll(means, covariances, probs, y):
  """-log sum_k p_k N(y | mu_k, Sigma_k) in nats; slots with p_k = 0 are left out.

  means (..., K, 2), covariances (..., K, 2, 2), probs (..., K), y (..., 2) -> (...,).
  """
  a, b, d = covariances[..., 0, 0], covariances[..., 0, 1], covariances[..., 1, 1]
  det = a * d - b * b
  dx, dy = (y[..., None, :] - means)[..., 0], (y[..., None, :] - means)[..., 1]
  maha = (d * dx * dx - 2.0 * b * dx * dy + a * dy * dy) / det
  log_pdf = -math.log(2.0 * math.pi) - 0.5 * jnp.log(det) - 0.5 * maha
  terms = jnp.where(probs > 0, jnp.log(jnp.where(probs > 0, probs, 1.0)) + log_pdf, -jnp.inf)
  return -jax.scipy.special.logsumexp(terms, axis=-1)


@jax.jit
def final_position_nll(samples, labels, probs, gt, floor: float = COVARIANCE_FLOOR_M2):
  """NLL (nats) of the true 5 s position under the hypotheses' Gaussian mixture.

  samples (..., N, T, 2) with their hypothesis labels (..., N), probs (..., K),
  gt (..., T, 2) -> (...,). See the module docstring.
  """
  means, cov = hypothesis_covariances(samples[..., -1, :], labels, probs.shape[-1], floor)
  return mixture_nll(means, cov, probs, gt[..., -1, :])


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Reliability:
  """Reliability-diagram data over NUM_BINS bins of predicted probability.

  Attributes:
    count: (NUM_BINS,) hypotheses in each bin.
    confidence: (NUM_BINS,) sum of their probabilities.
    correct: (NUM_BINS,) how many of them were the closest to the truth.
  """

  count: jax.Array
  confidence: jax.Array
  correct: jax.Array


@functools.partial(jax.jit, static_argnames="num_bins")
def reliability(probs, correct, valid, num_bins: int = NUM_BINS) -> Reliability:
  """Bins the valid hypotheses by probability: probs, correct, valid (..., K) ->
  `Reliability`; bin b holds p in [b / num_bins, (b + 1) / num_bins), the last bin
  also p = 1."""
  index = jnp.clip(jnp.floor(probs * num_bins).astype(jnp.int32), 0, num_bins - 1)
  one_hot = jax.nn.one_hot(index, num_bins, dtype=jnp.float32) * valid[..., None]
  flat = lambda w: jnp.sum((one_hot * w[..., None]).reshape(-1, num_bins), axis=0)
  return Reliability(
      count=flat(jnp.ones_like(probs, jnp.float32)),
      confidence=flat(probs.astype(jnp.float32)),
      correct=flat(correct.astype(jnp.float32)),
  )


@jax.jit
def expected_calibration_error(rel: Reliability):
  """sum_b (|B_b| / n) |accuracy_b - confidence_b| = sum_b |correct_b - confidence_b| / n."""
  return jnp.sum(jnp.abs(rel.correct - rel.confidence)) / jnp.maximum(jnp.sum(rel.count), 1.0)
