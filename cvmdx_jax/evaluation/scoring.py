"""Evaluation like the paper: cVMDx (mean, most likely p(c), best of K) against
constant velocity, constant acceleration + yaw rate and a single DDPM sample (cVMD),
overall and per maneuver class, as nested dicts (their markdown tables: `score_tables`).

Metrics per method and subset: `ade`, `fde` (m), `final_lon`, `final_lat` (|dx|, |dy|
at 5 s, m), `miss_rate` (final error > 2 m), `hit_rate` (final lateral error < 1.75 m),
`num_scenarios`. Best of K: ade / fde = minADE_K / minFDE_K, final_lon / final_lat and
miss_rate of the hypothesis with the smallest final error, hit_rate over any hypothesis,
plus `brier_min_fde` (Argoverse 2: minFDE_K + (1 - p)^2 of that hypothesis) and
`target_lane_hit` (lane changes only: a hypothesis with p >= 0.2 ends within 1.75 m of
the true final lateral position; absent from the kl subset), `nll_final` (nats, the true
5 s position under the hypotheses as a Gaussian mixture) and `ece` (calibration of p(c)
as "this hypothesis is the closest to the truth", 10 bins); `evaluation.probabilistic`
defines both. `energy_score` (m, `probabilistic`): of the N samples on the mean of N's
row, of the K hypotheses with their p on every best-of-K row, of the point mass on the
constant-velocity / -acceleration rows. The mean of N also carries
`out_of_distribution` (share of scenarios with delta beyond the tokeniser's training
range) and `delta_ade_spearman` / `delta_ade_spearman_p` (Spearman's rank correlation of
delta with the mean trajectory's ADE and its two-sided p-value).

Metrics are never computed over NaN: `check_finite` refuses non-finite predictions and
`summarise` non-finite per-scenario values, with `NonFinitePredictionError`.
"""

import jax
import jax.numpy as jnp
import numpy as np
from scipy import stats

from cvmdx_jax import constants
from cvmdx_jax.errors import UserError
from cvmdx_jax.evaluation import baselines, metrics, probabilistic

METHODS = ("cvmdx_mean", "cvmdx_most_likely", "cvmdx_best_of_k", "cv", "ca", "ddpm_single")
SUBSETS = ("all",) + constants.CLASS_NAMES
TARGET_LANE_MIN_PROB = 0.2  # a hypothesis counts for target_lane_hit from this probability


class NonFinitePredictionError(UserError):
  """A prediction (or a metric of it) holds NaN or inf; no metric is computed over it."""


def _name_scenarios(scenarios, index, limit: int = 10) -> str:
  """'#i (recording r, track t, frame f), ...' for the first `limit` of `index`."""
  names = [
      f"#{i} (recording {int(scenarios.recording_id[i])}, track "
      f"{int(scenarios.track_id[i])}, frame {int(scenarios.frame[i])})"
      for i in index[:limit]
  ]
  return ", ".join(names) + (f" and {len(index) - limit} more" if len(index) > limit else "")


def check_finite(prediction, scenarios, what: str) -> None:
  """Refuses a `Prediction` for `scenarios` whose arrays a metric reads (controls,
  trajectories, mean, hypothesis means and probs) hold NaN or inf anywhere.

  Raises:
    NonFinitePredictionError: naming `what` and the scenarios (position in `scenarios`,
      recording, track, frame).
  """
  hyp = prediction.hypotheses
  arrays = (prediction.controls, prediction.trajectories, prediction.mean, hyp.means, hyp.probs)
  m = len(scenarios)
  bad = np.zeros(m, bool)
  for a in arrays:
    bad |= ~np.isfinite(np.asarray(a).reshape(m, -1)).all(axis=1)
  if bad.any():
    raise NonFinitePredictionError(
        f"{what}: non-finite predictions for {int(bad.sum())} of {m} scenarios: "
        f"{_name_scenarios(scenarios, np.flatnonzero(bad))}"
    )


@jax.jit
def single_trajectory_errors(pred, gt) -> dict:
  """Per-scenario errors of one trajectory per scenario: (M, T, 2) each -> dict of (M,)."""
  final = metrics.fde(pred, gt)
  lon, lat = metrics.final_lon_lat(pred, gt)
  return {
      "ade": metrics.ade(pred, gt),
      "fde": final,
      "final_lon": lon,
      "final_lat": lat,
      "miss_rate": metrics.miss(final),
      "hit_rate": metrics.hit(pred, gt),
  }


def best_of_k_errors(hyps, probs, gt, labels) -> dict:
  """Per-scenario best-of-K errors over the used hypothesis slots.

  hyps (M, K, T, 2), probs (M, K) (0 = unused slot), gt (M, T, 2), labels (M,).
  `target_lane_hit` is a masked array, masked on keep-lane scenarios; `energy_score` is the
  exact score of the hypotheses as a discrete distribution with weights p.
  """
  errors = _best_of_k(hyps, probs, gt)
  lane = errors["target_lane_hit"]
  return {**errors, "target_lane_hit": np.ma.masked_array(lane, mask=np.asarray(labels) == 0)}


@jax.jit
def _best_of_k(hyps, probs, gt) -> dict:
  """`best_of_k_errors` but for the mask of `target_lane_hit`."""
  valid = probs > 0
  final = metrics.min_fde_k(hyps, gt, valid)
  lon, lat = metrics.final_lon_lat(
      metrics.take_hypothesis(hyps, metrics.closest_final(hyps, gt, valid)), gt
  )
  hits = jnp.where(valid, metrics.hit(hyps, gt[:, None]), 0.0)
  weights = probs / jnp.sum(probs, axis=-1, keepdims=True)
  return {
      "ade": metrics.min_ade_k(hyps, gt, valid),
      "fde": final,
      "final_lon": lon,
      "final_lat": lat,
      "miss_rate": metrics.miss(final),
      "hit_rate": jnp.max(hits, axis=-1),
      "brier_min_fde": metrics.brier_min_fde(hyps, probs, gt, valid),
      "target_lane_hit": metrics.target_lane_hit(hyps, probs, gt, min_prob=TARGET_LANE_MIN_PROB),
      "energy_score": probabilistic.weighted_energy_score(hyps, weights, gt, fair=False),
  }


def cvmdx_errors(output, gt, labels) -> dict:
  """The three cVMDx read-outs of a `PredictorOutput` -> {method: per-scenario errors};
  the mean's also hold `out_of_distribution` (1.0 where flagged) and `energy_score`,
  best of K's `nll_final`."""
  prediction, hyp = output.prediction, output.hypotheses
  mean = single_trajectory_errors(prediction.mean, gt)
  return {
      "cvmdx_mean": {
          **mean,
          "out_of_distribution": np.asarray(output.out_of_distribution, np.float64),
          "energy_score": probabilistic.energy_score(prediction.trajectories, gt),
      },
      "cvmdx_most_likely": single_trajectory_errors(metrics.most_likely(hyp.means, hyp.probs), gt),
      "cvmdx_best_of_k": {
          **best_of_k_errors(hyp.means, hyp.probs, gt, labels),
          "nll_final": probabilistic.final_position_nll(
              prediction.trajectories, hyp.labels, hyp.probs, gt
          ),
      },
  }


def calibration(hyps, probs, gt, labels) -> tuple[dict, dict]:
  """Calibration of hypothesis probabilities per subset.

  hyps (M, K, T, 2), probs (M, K) (0 = unused slot), gt (M, T, 2), labels (M,).
  Returns ({subset: {"ece": value}} (NaN for an empty subset), the reliability-diagram
  data of all scenarios as lists: {"count", "confidence", "accuracy"} per bin, with
  confidence and accuracy the bin's means (NaN where empty)).
  """
  valid, correct = _closest(hyps, probs, gt)
  out = {}
  for subset, sel in _subset_masks(np.asarray(labels)):  # a subset as a mask: one shape
    rel = probabilistic.reliability(probs, correct, valid & sel[:, None])
    out[subset] = {
        "ece": float(probabilistic.expected_calibration_error(rel)) if sel.any() else float("nan")
    }
  rel = probabilistic.reliability(probs, correct, valid)
  count = np.asarray(rel.count, np.float64)
  with np.errstate(invalid="ignore", divide="ignore"):
    diagram = {
        "count": count.tolist(),
        "confidence": (np.asarray(rel.confidence) / count).tolist(),
        "accuracy": (np.asarray(rel.correct) / count).tolist(),
    }
  return out, diagram


@jax.jit
def _closest(hyps, probs, gt):
  """(valid (M, K): p > 0, correct (M, K): the valid hypothesis closest to the truth at 5 s)."""
  valid = probs > 0
  closest = metrics.closest_final(hyps, gt, valid)
  return valid, jnp.arange(probs.shape[-1]) == closest[:, None]


def delta_rank_correlation(delta, ade, labels) -> dict:
  """Spearman's rank correlation of delta with an ADE, per subset.

  delta, ade, labels: (M,). Returns {subset: {"delta_ade_spearman": rho,
  "delta_ade_spearman_p": two-sided p}}; NaN where a subset has < 3 scenarios or a
  constant delta or ADE.
  """
  delta, ade, labels = (np.asarray(a) for a in (delta, ade, labels))
  out = {}
  for subset, sel in _subset_masks(labels):
    rho = p = float("nan")
    if sel.sum() >= 3 and np.ptp(delta[sel]) > 0 and np.ptp(ade[sel]) > 0:
      rho, p = (float(v) for v in stats.spearmanr(delta[sel], ade[sel]))
    out[subset] = {"delta_ade_spearman": rho, "delta_ade_spearman_p": p}
  return out


def baseline_errors(scenarios) -> dict:
  """Constant velocity and constant acceleration + yaw rate; their `energy_score` is that of
  a point mass (the root-mean-square displacement)."""
  gt = jnp.asarray(scenarios.future)
  point_mass = lambda pred: {
      **single_trajectory_errors(pred, gt),
      "energy_score": probabilistic.energy_score(pred[:, None], gt),
  }
  return {
      "cv": point_mass(baselines.constant_velocity(scenarios.xi)),
      "ca": point_mass(baselines.constant_acceleration_yaw_rate(scenarios.xi)),
  }


def _subset_masks(labels):
  """(subset name, (M,) bool selection) for each of `SUBSETS`."""
  return [
      (s, np.ones_like(labels, bool) if s == "all" else labels == SUBSETS.index(s) - 1)
      for s in SUBSETS
  ]


def summarise(errors: dict, labels) -> dict:
  """{method: per-scenario errors} + labels (M,) -> {method: {subset: {metric: value}}}.

  A subset's value is the mean over its scenarios (NaN for an empty subset). A metric
  given as a masked array averages its unmasked scenarios only and is left out of a
  subset where all are masked.

  Raises:
    NonFinitePredictionError: a per-scenario value is NaN or inf (naming the method,
      metric and scenario positions).
  """
  labels = np.asarray(labels)
  out = {}
  for method, per in errors.items():
    per = {k: np.ma.asarray(v, np.float64) for k, v in per.items()}
    for k, v in per.items():
      bad = np.flatnonzero(~np.isfinite(v.filled(0.0)))
      if len(bad):
        raise NonFinitePredictionError(
            f"{method} {k} is not finite for scenarios at " f"positions {bad[:10].tolist()}"
        )
    out[method] = {}
    for subset, sel in _subset_masks(labels):
      row = {}
      for k, v in per.items():
        if not sel.any():
          row[k] = float("nan")
        elif v[sel].count():
          row[k] = float(v[sel].mean())
      out[method][subset] = {**row, "num_scenarios": int(sel.sum())}
  return out
