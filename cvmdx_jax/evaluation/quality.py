"""The quality benchmark of one trained demo: every model's proper scores on large test
sets, with settings chosen on val and regions calibrated on validation scenarios.

`evaluate_run` predicts every model (`predictive`) on val (the run's own), on the
calibration scenarios, then on each evaluated split; on val it chooses each model's kernel
rules (`model_scores`), on the calibration scenarios (validation scenarios not used for
anything else; val itself where none are given) it calibrates each model's region levels
per horizon (`conformal`, plain and per delta tercile) and its p(c) threshold; on each
evaluated split the online levels start from the plain ones and follow the split's truths
in time order (`stream_times`, `conformal.online_levels`). It returns plain data
(`RunScores`); `quality_tables` renders it.
"""

import dataclasses

import jax
import numpy as np

from cvmdx_jax import constants
from cvmdx_jax.evaluation import (
    conformal,
    model_scores,
    predictive,
    prob_calibration,
    regions,
)

CALIBRATION_LEVEL = 0.9  # the region level calibrated and reported with and without delta


@dataclasses.dataclass(frozen=True)
class RunScores:
  """One trained run's scores.

  Attributes:
    bandwidths: {model: per horizon the rule (c, f_lon m, f_lat m, eps, lam) or None}, chosen
      on val (`regions`).
    levels: {model: {"plain": (5,) calibrated levels per horizon, "delta": (3, 5) per delta
      tercile}} of `CALIBRATION_LEVEL`, and {"pc": threshold} for the K-set models.
    splits: {split: {"meta": {recording_id, track_id, frame, label, delta} (M,),
      model: {score: (M,)}}}; region scores also `cal_cover_<s>s`, `cal_area_<s>s`,
      `delta_cover_<s>s`, `delta_area_<s>s` (calibrated 90 % regions), `online_level_<s>s`,
      `online_cover_<s>s`, `online_area_<s>s` (online 90 % regions, `conformal`), and for K-sets
      `pc_cover`, `pc_size` (raw 0.9 threshold) and `pc_cal_cover`, `pc_cal_size`.
  """

  bandwidths: dict
  levels: dict
  splits: dict


def _models(predictor, baseline, mdn_fn, scenarios, seed: int) -> list:
  out = predictor(scenarios, seed=seed)
  models = predictive.cvmdx_models(out) + predictive.physics_models(scenarios)
  if baseline is not None:
    models.append(predictive.mlp_model(baseline, out, scenarios))
  if mdn_fn is not None:
    models += predictive.mdn_models(mdn_fn(out, scenarios))
  return models, np.asarray(out.delta)


def _closest(model, gt):
  k = model.k_set
  return prob_calibration.closest_hypothesis(k.points, k.weights, gt)


def conformity_scores(model, bandwidths, gt, key) -> np.ndarray:
  """(M, H) u of the true positions gt (M, 125, 2) at each of `regions.HORIZON_STEPS`
  (`regions.hdr`), the Monte Carlo key folded with the horizon's index."""
  return np.stack(
      [
          regions.hdr(
              jax.random.fold_in(key, i),
              model_scores.density_at(model, bandwidths, i),
              gt[:, step],
              (CALIBRATION_LEVEL,),
          )[0]
          for i, step in enumerate(regions.HORIZON_STEPS)
      ],
      axis=1,
  )


def _calibrate(model, bandwidths, scenarios, delta, key) -> dict:
  """Val u per horizon -> calibrated levels (plain and per delta tercile), p(c) threshold."""
  gt = np.asarray(scenarios.future, np.float32)
  edges = conformal.bin_edges(delta)
  bins = np.digitize(delta, edges)
  plain, by_delta = [], []
  for u in conformity_scores(model, bandwidths, gt, key).T:
    plain.append(conformal.calibrated_level(u, CALIBRATION_LEVEL))
    by_delta.append(
        [
            conformal.calibrated_level(u[bins == b], CALIBRATION_LEVEL)
            for b in range(conformal.DELTA_BINS)
        ]
    )
  out = {"plain": np.asarray(plain), "delta": np.asarray(by_delta).T, "delta_edges": edges}
  if model.k_set is not None:
    scores = conformal.hypothesis_scores(model.k_set.weights, _closest(model, gt))
    out["pc"] = conformal.calibrated_level(scores, CALIBRATION_LEVEL)
  return out


def _scenario_levels(levels, delta):
  """Per horizon the (M, 2) calibrated levels of each scenario: plain, its delta tercile's."""
  bins = np.digitize(delta, levels["delta_edges"])
  return [
      np.stack([np.full(len(delta), levels["plain"][i]), levels["delta"][bins, i]], 1)
      for i in range(len(regions.HORIZONS_S))
  ]


def stream_times(scenarios) -> tuple[np.ndarray, int]:
  """(M,) times in frames on one clock, and the frames a truth takes per second of horizon:
  the recordings one after another (by id), each after the last one's truths are known.
  Where a frame is unknown (-1): the scenarios' order, each truth known before the next."""
  frame = np.asarray(scenarios.frame, np.int64)
  if len(frame) == 0 or np.any(frame < 0):
    return np.arange(len(frame)), 0
  recording = np.unique(np.asarray(scenarios.recording_id), return_inverse=True)[1]
  return recording * (int(frame.max()) + constants.T_PRED + 1) + frame, constants.FRAME_RATE_HZ


def _online(levels, scenarios):
  """`model_scores.scenario_scores`' online levels: adaptive conformal from the plain
  calibrated level, with the truth at horizon s known s seconds after the prediction."""
  times, per_s = stream_times(scenarios)

  def levels_at(i, u):
    start = float(levels["plain"][i])
    return conformal.online_levels(
        u,
        times,
        per_s * regions.HORIZONS_S[i],
        start,
        CALIBRATION_LEVEL,
        conformal.aci_gamma(start, len(u)),
    )

  return levels_at


def _score(model, bandwidths, levels, scenarios, delta, key) -> dict:
  """`model_scores.scenario_scores` plus coverage and area of the calibrated regions (split
  conformal, per delta tercile, online) and the p(c) sets, per scenario."""
  gt = np.asarray(scenarios.future, np.float32)
  per = _scenario_levels(levels, delta)
  online = _online(levels, scenarios) if len(gt) * conformal.ACI_TOLERANCE > 1 else None
  out = model_scores.scenario_scores(model, gt, bandwidths, key, extra_levels=per, online=online)
  for i, s in enumerate(regions.HORIZONS_S):
    u = out[f"hdr_u_{s}s"]
    out.update(
        {
            f"cal_cover_{s}s": (u <= per[i][:, 0]).astype(float),
            f"cal_area_{s}s": out.pop(f"area_x0_{s}s"),
            f"delta_cover_{s}s": (u <= per[i][:, 1]).astype(float),
            f"delta_area_{s}s": out.pop(f"area_x1_{s}s"),
        }
    )
    if online is not None:
      out[f"online_cover_{s}s"] = (u <= out[f"online_level_{s}s"]).astype(float)
  if "pc" in levels:
    scores = conformal.hypothesis_scores(model.k_set.weights, _closest(model, gt))
    for tag, threshold in (("pc", CALIBRATION_LEVEL), ("pc_cal", levels["pc"])):
      out[f"{tag}_cover"] = (scores <= threshold + 1e-9).astype(float)
      out[f"{tag}_size"] = conformal.hypothesis_set_size(model.k_set.weights, threshold)
  return out


def _pooled(models_by_set: list, deltas: list, sets: list):
  """The calibration sets' models, deltas and scenarios concatenated per model."""
  if len(sets) == 1:
    return models_by_set[0], deltas[0], sets[0]
  cat = lambda *a: np.concatenate([np.asarray(x) for x in a])
  models = [
      dataclasses.replace(
          group[0],
          distribution=jax.tree.map(cat, *[m.distribution for m in group]),
          k_set=None if group[0].k_set is None else jax.tree.map(cat, *[m.k_set for m in group]),
          labels=None if group[0].labels is None else cat(*[m.labels for m in group]),
      )
      for group in zip(*models_by_set)
  ]
  return models, cat(*deltas), jax.tree.map(cat, *sets)


def evaluate_run(
    predictor, baseline, mdn_fn, val, splits: dict, calibration=(), seed: int = 0, log=print
) -> RunScores:
  """Scores one trained run.

  Args:
    predictor: `inference.predictor.Predictor` (tokeniser + denoiser).
    baseline: the WTA MLP (`LearnedBaseline`) or None.
    mdn_fn: (PredictorOutput, Scenarios) -> `GaussianMixture`, or None.
    val: the run's val `Scenarios` (chooses the kernel rules; calibrates the levels where
      `calibration` is empty).
    splits: {name: Scenarios} to score.
    calibration: `Scenarios` sets pooled to calibrate the levels.
    seed: sampling and Monte Carlo seed.
  """
  key = jax.random.key(seed)
  val_models, val_delta = _models(predictor, baseline, mdn_fn, val, seed)
  val_gt = np.asarray(val.future, np.float32)
  bandwidths, levels = {}, {}
  for model in val_models:
    bandwidths[model.name] = model_scores.choose_bandwidths(model, val_gt)
    log(f"  val: {model.name} kernel rules {bandwidths[model.name]}")
  if calibration:
    found = [_models(predictor, baseline, mdn_fn, s, seed) for s in calibration]
    cal_models, cal_delta, cal = _pooled(
        [f[0] for f in found], [f[1] for f in found], list(calibration)
    )
  else:
    cal_models, cal_delta, cal = val_models, val_delta, val
  for model in cal_models:
    levels[model.name] = _calibrate(
        model, bandwidths[model.name], cal, cal_delta, jax.random.fold_in(key, 1)
    )
    log(f"  calibration ({len(cal_delta)}): {model.name} levels {levels[model.name]['plain']}")
  scored = {}
  for name, scenarios in splits.items():
    models, delta = _models(predictor, baseline, mdn_fn, scenarios, seed)
    meta = {
        "recording_id": np.asarray(scenarios.recording_id),
        "frame": np.asarray(scenarios.frame),
        "track_id": np.asarray(scenarios.track_id),
        "label": np.asarray(scenarios.label),
        "delta": delta,
    }
    scored[name] = {"meta": meta}
    for model in models:
      scored[name][model.name] = _score(
          model,
          bandwidths[model.name],
          levels[model.name],
          scenarios,
          delta,
          jax.random.fold_in(key, 2),
      )
    log(f"  {name}: {len(scenarios)} scenarios scored")
  return RunScores(bandwidths=bandwidths, levels=levels, splits=scored)
