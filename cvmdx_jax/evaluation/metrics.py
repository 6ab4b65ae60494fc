"""Trajectory metrics in metres (Euclidean), channels-last (..., T, 2).

Hypothesis sets carry a validity mask (probability > 0) so that unused GMM slots
never count in best-of-K metrics.
"""

import jax.numpy as jnp

MISS_THRESHOLD_M = 2.0  # final displacement above which a prediction misses
HIT_LATERAL_M = 1.75  # final lateral error below which a prediction hits (half a lane)


def displacement(pred, gt):
  """(..., T, 2), (..., T, 2) -> (..., T) Euclidean error per step."""
  return jnp.linalg.norm(pred - gt, axis=-1)


def ade(pred, gt):
  """Average displacement error over all steps: (..., T, 2) -> (...,)."""
  return jnp.mean(displacement(pred, gt), axis=-1)


def fde(pred, gt):
  """Final displacement error (last step, 5 s): (..., T, 2) -> (...,)."""
  return displacement(pred[..., -1, :], gt[..., -1, :])


def _per_hypothesis(fn, hyps, gt, valid):
  err = fn(hyps, gt[..., None, :, :])  # (..., K)
  return jnp.where(valid, err, jnp.inf)


def min_ade_k(hyps, gt, valid):
  """minADE_K over K hypotheses: hyps (..., K, T, 2), gt (..., T, 2), valid (..., K) -> (...,)."""
  return jnp.min(_per_hypothesis(ade, hyps, gt, valid), axis=-1)


def min_fde_k(hyps, gt, valid):
  """minFDE_K over K hypotheses (see `min_ade_k`)."""
  return jnp.min(_per_hypothesis(fde, hyps, gt, valid), axis=-1)


def take_hypothesis(hyps, idx):
  """Hypothesis `idx` of each set: (..., K, T, 2), int (...,) -> (..., T, 2)."""
  return jnp.take_along_axis(hyps, idx[..., None, None, None], axis=-3)[..., 0, :, :]


def most_likely(hyps, probs):
  """The hypothesis with the highest probability: (..., K, T, 2), (..., K) -> (..., T, 2)."""
  return take_hypothesis(hyps, jnp.argmax(probs, axis=-1))


def closest_final(hyps, gt, valid):
  """Index of the valid hypothesis with the smallest final error (the one minFDE_K
  picks): (..., K, T, 2), (..., T, 2), (..., K) -> int (...,)."""
  return jnp.argmin(_per_hypothesis(fde, hyps, gt, valid), axis=-1)


def miss(pred_final_error):
  """1.0 where the final displacement exceeds 2 m."""
  return (pred_final_error > MISS_THRESHOLD_M).astype(jnp.float32)


def hit(pred, gt):
  """1.0 where the final lateral error is below 1.75 m: (..., T, 2) -> (...,)."""
  return (jnp.abs(pred[..., -1, 1] - gt[..., -1, 1]) < HIT_LATERAL_M).astype(jnp.float32)


def final_lon_lat(pred, gt):
  """Final longitudinal and lateral errors |dx(5 s)|, |dy(5 s)|: (..., T, 2) -> two (...,)."""
  err = jnp.abs(pred[..., -1, :] - gt[..., -1, :])
  return err[..., 0], err[..., 1]


def brier_min_fde(hyps, probs, gt, valid):
  """Brier-minFDE (Argoverse 2): minFDE_K + (1 - p)^2 with p the probability of the
  hypothesis that attains minFDE_K. hyps (..., K, T, 2), probs and valid (..., K),
  gt (..., T, 2) -> (...,)."""
  err = _per_hypothesis(fde, hyps, gt, valid)
  best = jnp.argmin(err, axis=-1)[..., None]  # `closest_final`, from err in hand
  p = jnp.take_along_axis(probs, best, axis=-1)[..., 0]
  return jnp.take_along_axis(err, best, axis=-1)[..., 0] + (1.0 - p) ** 2


def target_lane_hit(hyps, probs, gt, min_prob: float = 0.2):
  """1.0 where a hypothesis with p >= min_prob ends in the lane the ego ends in: its
  final lateral position within half a lane (1.75 m) of the ground truth's.
  hyps (..., K, T, 2), probs (..., K), gt (..., T, 2) -> (...,)."""
  ends = hit(hyps, gt[..., None, :, :]) * (probs >= min_prob)
  return jnp.max(ends, axis=-1)
