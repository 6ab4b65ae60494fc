"""Per-scenario scores of any model's predictive distribution, with the same definitions.

A model is a `Model`: a name, its distribution (`WeightedSamples` or `GaussianMixture`),
whether its weighted points are samples drawn from a model (`fair`: cVMDx's N samples, an
MDN sampled) or the distribution itself (heads with their p, hypotheses, a point mass),
optionally its K-set (hypotheses / heads / modes with their probabilities) for the
best-of-K metrics, and optionally a cluster per point (`labels`: the density is then a
Gaussian per cluster, `regions.components`). `scenario_scores` returns, per scenario (M,):

- `energy_score` (m, `probabilistic.weighted_energy_score`; a mixture sampled with
  `ES_SAMPLES` draws, fair);
- `nll_<s>s` (nats) and `hdr_u_<s>s` (the mass of the smallest highest-density region
  holding the truth; inside the level-a region iff u <= a) at s = 1..5 (`regions`; the
  kernel and tail rules from `choose_bandwidths` on val), `area_<pct>_<s>s` (m^2) of the
  50 / 90 / 95 % regions;
- `ade`, `fde`, `sq_err_<s>s` (m, m^2) of the mean trajectory (RMSE at s = the root of the
  mean of `sq_err_<s>s`);
- given a K-set: `min_ade`, `min_fde`, `miss_rate`, `brier_min_fde` (`scoring.best_of_k_errors`)
  and `closest_log_loss` (nats: -log p of the hypothesis closest at 5 s, the one Brier-minFDE
  charges (1 - p)^2 for; `prob_calibration`).
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from cvmdx_jax.evaluation import metrics, prob_calibration, probabilistic, regions, scoring
from cvmdx_jax.inference.distributions import GaussianMixture, WeightedSamples

ES_SAMPLES = 64  # draws of a GaussianMixture for its energy score
_ES_CHUNK = 512


@dataclasses.dataclass(frozen=True)
class Model:
  """A named predictive distribution (see the module docstring)."""

  name: str
  distribution: WeightedSamples | GaussianMixture
  fair: bool = False
  k_set: WeightedSamples | None = None
  labels: np.ndarray | None = None  # (M, N) int cluster of each point


def choose_bandwidths(model: Model, gt) -> tuple:
  """Per horizon of `regions.HORIZON_STEPS` the rule (c, f_lon m, f_lat m, eps, lam) chosen on
  these scenarios (give val; `regions.choose_bandwidth`); None for a mixture (its own
  density)."""
  if isinstance(model.distribution, GaussianMixture):
    return None
  return tuple(
      regions.choose_bandwidth(model.distribution, gt, step, labels=model.labels)
      for step in regions.HORIZON_STEPS
  )


def density_at(model: Model, bandwidths, i: int) -> regions.HorizonMixture:
  """`model`'s density at the i-th of `regions.HORIZON_STEPS`, with its rule from
  `choose_bandwidths` (None for a mixture) and its clusters."""
  rule = None if bandwidths is None else bandwidths[i]
  return regions.at_horizon(model.distribution, regions.HORIZON_STEPS[i], rule, model.labels)


def _energy_scores(model: Model, gt, key) -> np.ndarray:
  dist, fair = model.distribution, model.fair
  if isinstance(dist, GaussianMixture):
    dist, fair = dist.sample(key, ES_SAMPLES), True
  out = [
      probabilistic.weighted_energy_score(
          jnp.asarray(dist.points[i : i + _ES_CHUNK]),
          jnp.asarray(dist.weights[i : i + _ES_CHUNK]),
          jnp.asarray(gt[i : i + _ES_CHUNK]),
          fair,
      )
      for i in range(0, len(gt), _ES_CHUNK)
  ]
  return np.concatenate([np.asarray(a) for a in out])


def scenario_scores(
    model: Model, gt, bandwidths, key: jax.Array, extra_levels=None, online=None
) -> dict:
  """Per-scenario scores (module docstring) of `model` against gt (M, 125, 2).

  bandwidths: `choose_bandwidths` of the same model on val. extra_levels: per horizon an
  (M, E) array of further region masses per scenario (calibrated levels), whose areas come
  back as `area_x<j>_<s>s` from the same draws. online: (horizon index, u (M,)) -> (M,)
  levels that depend on the scores (`conformal.online_levels`), returned as
  `online_level_<s>s` with their areas `online_area_<s>s` from the same draws.
  """
  gt = np.asarray(gt, np.float32)
  es_key, hdr_key = jax.random.split(key)
  out = {"energy_score": _energy_scores(model, gt, es_key)}
  nominal = np.broadcast_to(np.asarray(regions.LEVELS, np.float32), (len(gt), len(regions.LEVELS)))
  for i, (s, step) in enumerate(zip(regions.HORIZONS_S, regions.HORIZON_STEPS)):
    mix = density_at(model, bandwidths, i)
    out[f"nll_{s}s"] = np.asarray(regions.nll(mix, gt[:, step]))
    levels = (
        nominal
        if extra_levels is None
        else np.concatenate([nominal, np.asarray(extra_levels[i], np.float32)], axis=1)
    )
    u, area = regions.hdr(jax.random.fold_in(hdr_key, s), mix, gt[:, step], levels)
    out[f"hdr_u_{s}s"] = u
    if online is not None:
      out[f"online_level_{s}s"] = online(i, u)
      out[f"online_area_{s}s"] = regions.hdr(
          jax.random.fold_in(hdr_key, s), mix, gt[:, step], out[f"online_level_{s}s"][:, None]
      )[1][:, 0]
    for j in range(area.shape[1]):
      tag = (
          f"{round(100 * regions.LEVELS[j])}"
          if j < len(regions.LEVELS)
          else f"x{j - len(regions.LEVELS)}"
      )
      out[f"area_{tag}_{s}s"] = area[:, j]
  mean = np.asarray(model.distribution.mean())
  out["ade"] = np.asarray(metrics.ade(mean, gt))
  out["fde"] = np.asarray(metrics.fde(mean, gt))
  for s, step in zip(regions.HORIZONS_S, regions.HORIZON_STEPS):
    out[f"sq_err_{s}s"] = np.sum((mean[:, step] - gt[:, step]) ** 2, axis=-1)
  if model.k_set is not None:
    probs = jnp.maximum(jnp.asarray(model.k_set.weights), 0.0)
    best = scoring.best_of_k_errors(
        jnp.asarray(model.k_set.points), probs, jnp.asarray(gt), np.zeros(len(gt), int)
    )
    out.update(
        min_ade=np.asarray(best["ade"]),
        min_fde=np.asarray(best["fde"]),
        miss_rate=np.asarray(best["miss_rate"]),
        brier_min_fde=np.asarray(best["brier_min_fde"]),
        closest_log_loss=prob_calibration.closest_log_loss(
            probs, prob_calibration.closest_hypothesis(model.k_set.points, probs, gt)
        ),
    )
  return out
