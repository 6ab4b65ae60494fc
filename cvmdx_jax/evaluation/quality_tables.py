"""Markdown tables and summary data of the quality benchmark (`quality.RunScores` per seed).

Values per seed are means over scenarios (RMSE: the root of the mean squared error);
summary tables show the mean over seeds. Comparisons are paired differences over the same
scenarios with 95 % vehicle-bootstrap intervals (`intervals`), one column per seed; a
difference is "better" / "worse" only where its interval excludes 0.
"""

import numpy as np

from cvmdx_jax import constants
from cvmdx_jax.evaluation import intervals, predictive, region_groups, regions

SUBSETS = ("all",) + constants.CLASS_NAMES
LEARNED = ("mlp_heads", "mdn")
BASELINES = ("cv", "ca") + LEARNED
HEADS = ("mlp_heads", "mdn_modes", "mdn")  # what cVMDx's K hypotheses are compared with
PC_MODELS = ("cvmdx_hypotheses",) + LEARNED  # K-sets with probabilities of their own
_SUMMARY = (
    ("energy_score", "ES [m]"),
    ("nll_1s", "NLL 1 s"),
    ("nll_3s", "NLL 3 s"),
    ("nll_5s", "NLL 5 s"),
    ("rmse_1s", "RMSE 1 s"),
    ("rmse_2s", "RMSE 2 s"),
    ("rmse_3s", "RMSE 3 s"),
    ("rmse_4s", "RMSE 4 s"),
    ("rmse_5s", "RMSE 5 s"),
    ("ade", "ADE"),
    ("fde", "FDE"),
    ("min_ade", "minADE_K"),
    ("min_fde", "minFDE_K"),
    ("brier_min_fde", "Brier-minFDE"),
    ("closest_log_loss", "log loss p(closest)"),
    ("miss_rate", "miss rate"),
    ("cover_50_5s", "cover 50 % 5 s"),
    ("cover_90_5s", "cover 90 % 5 s"),
    ("cover_95_5s", "cover 95 % 5 s"),
    ("area_90_5s", "area 90 % 5 s [m^2]"),
)


def value(row: dict, metric: str, select=None) -> float:
  """A metric's mean over (the selected) scenarios; rmse_<s>s and cover_<pct>_<s>s derived."""
  sel = slice(None) if select is None else select
  if metric.startswith("rmse_"):
    return float(np.sqrt(np.mean(row["sq_err_" + metric[5:]][sel])))
  if metric.startswith("cover_"):
    pct, horizon = metric[6:].split("_")
    return float(np.mean(row[f"hdr_u_{horizon}"][sel] <= int(pct) / 100.0))
  return float(np.mean(row[metric][sel])) if metric in row else float("nan")


def _select(meta, subset):
  return (
      np.ones(len(meta["label"]), bool)
      if subset == "all"
      else (meta["label"] == SUBSETS.index(subset) - 1)
  )


def summary(runs: dict, split: str) -> dict:
  """{model: {metric: mean over seeds}} on `split` (runs: {seed: RunScores})."""
  out = {}
  for scores in runs.values():
    for model, row in scores.splits[split].items():
      if model == "meta":
        continue
      for metric, _ in _SUMMARY:
        out.setdefault(model, {}).setdefault(metric, []).append(value(row, metric))
  return {m: {k: float(np.mean(v)) for k, v in r.items()} for m, r in out.items()}


def comparisons(models) -> list:
  """(a, b, metric, subset, kind) of every reported paired comparison among `models`."""
  rows = []
  for b in (m for m in BASELINES if m in models):
    rows += [
        ("cvmdx_samples", b, metric, "all", "mean")
        for metric in ("energy_score", "nll_1s", "nll_3s", "nll_5s")
    ]
  for b in (m for m in HEADS if m in models):
    rows += [
        ("cvmdx_hypotheses", b, metric, "all", "mean")
        for metric in ("energy_score", "brier_min_fde", "min_fde", "closest_log_loss")
    ]
  for b in (m for m in BASELINES if m in models):
    rows += [
        ("cvmdx_samples", b, metric, subset, "mean")
        for metric in ("ade", "fde")
        for subset in SUBSETS
    ]
    rows.append(("cvmdx_samples", b, "sq_err_5s", "all", "rmse"))
  return rows


def differences(runs: dict, split: str) -> list:
  """Per comparison: {"a", "b", "metric", "subset", "by_seed": {seed: paired_difference}}."""
  out = []
  first = next(iter(runs.values())).splits[split]
  for a, b, metric, subset, kind in comparisons([m for m in first if m != "meta"]):
    if metric not in first[a] or metric not in first[b]:
      continue  # scores saved before the metric existed (--reuse)
    by_seed = {}
    for seed, scores in runs.items():
      data = scores.splits[split]
      sel = _select(data["meta"], subset)
      groups = intervals.vehicle_groups(
          data["meta"]["recording_id"][sel], data["meta"]["track_id"][sel]
      )
      fa, fb = data[a][metric][sel], data[b][metric][sel]
      if kind == "rmse":
        fa, fb = np.sqrt(fa), np.sqrt(fb)
      by_seed[seed] = intervals.paired_difference(fa, fb, groups, kind=kind)
    out.append(
        {
            "a": a,
            "b": b,
            "metric": "rmse_5s" if kind == "rmse" else metric,
            "subset": subset,
            "by_seed": by_seed,
        }
    )
  return out


def _fmt(x, spec="{:.3f}"):
  return "n/a" if x != x else spec.format(x)


def summary_table(table: dict) -> str:
  """One row per model, the columns of `_SUMMARY`."""
  lines = [
      "| model | " + " | ".join(title for _, title in _SUMMARY) + " |",
      "|---|" + "---|" * len(_SUMMARY),
  ]
  for model, row in table.items():
    lines.append(
        f"| {predictive.TITLES.get(model, model)} | "
        + " | ".join(_fmt(row[k]) for k, _ in _SUMMARY)
        + " |"
    )
  return "\n".join(lines) + "\n"


def difference_table(rows: list) -> str:
  """One row per comparison, one column per seed: 'difference [low, high] verdict'."""
  seeds = list(rows[0]["by_seed"]) if rows else []
  lines = [
      "| a - b | metric | subset | " + " | ".join(f"seed {s}" for s in seeds) + " |",
      "|---|---|---|" + "---|" * len(seeds),
  ]
  for r in rows:
    cells = " | ".join(intervals.format_difference(r["by_seed"][s]) for s in seeds)
    lines.append(f"| {r['a']} - {r['b']} | {r['metric']} | {r['subset']} | {cells} |")
  return "\n".join(lines) + "\n"


def calibration_table(runs: dict, splits) -> str:
  """Coverage of the 90 % regions at 1..5 s (raw, calibrated, per delta tercile) and
  their areas at 5 s, mean over seeds, per model and split."""
  h = regions.HORIZONS_S
  head = (
      "| model | split | "
      + " | ".join(f"raw {s} s" for s in h)
      + " | "
      + " | ".join(f"cal {s} s" for s in h)
      + " | "
      + " | ".join(f"delta {s} s" for s in h)
      + " | area 5 s raw / cal / delta [m^2] |"
  )
  lines = [head, "|---|---|" + "---|" * (3 * len(h) + 1)]
  first = next(iter(runs.values())).splits
  for model in (m for m in first[splits[0]] if m != "meta"):
    for split in splits:
      mean = lambda k: float(np.mean([value(r.splits[split][model], k) for r in runs.values()]))
      cells = (
          [mean(f"cover_90_{s}s") for s in h]
          + [mean(f"cal_cover_{s}s") for s in h]
          + [mean(f"delta_cover_{s}s") for s in h]
      )
      areas = " / ".join(
          _fmt(mean(k), "{:.1f}") for k in ("area_90_5s", "cal_area_5s", "delta_area_5s")
      )
      lines.append(
          f"| {predictive.TITLES.get(model, model)} | {split} | "
          + " | ".join(_fmt(c, "{:.3f}") for c in cells)
          + f" | {areas} |"
      )
  return "\n".join(lines) + "\n"


def recording_table(runs: dict, splits, model: str = "cvmdx_samples") -> str:
  """Coverage of `model`'s calibrated 90 % regions (plain, per delta tercile) at 1..5 s per
  recording of each split, mean over seeds (the seeds score the same scenarios)."""
  h = regions.HORIZONS_S
  lines = [
      "| split | recording | scenarios | "
      + " | ".join(f"cal {s} s" for s in h)
      + " | "
      + " | ".join(f"delta {s} s" for s in h)
      + " |",
      "|---|---|---|" + "---|" * (2 * len(h)),
  ]
  for split in splits:
    found = [r.splits[split] for r in runs.values() if model in r.splits[split]]
    if not found:
      continue
    cover = {}
    for k in (f"{kind}_cover_{s}s" for kind in ("cal", "delta") for s in h):
      per_seed = [
          region_groups.recording_coverage(f[model][k], f["meta"]["recording_id"]) for f in found
      ]
      ids, counts = per_seed[0][:2]
      cover[k] = np.mean([c for _, _, c in per_seed], axis=0)
    for r, (rec, n) in enumerate(zip(ids, counts)):
      cells = " | ".join(f"{cover[k][r]:.3f}" for k in cover)
      lines.append(f"| {split} | {rec} | {n} | {cells} |")
  return "\n".join(lines) + "\n"


def hypothesis_set_table(runs: dict, splits) -> str:
  """p(c) sets: coverage of the closest hypothesis and mean set size, raw 0.9 threshold
  and calibrated, mean over seeds."""
  lines = [
      "| model | split | raw cover | raw size | calibrated cover | calibrated size |",
      "|---|---|---|---|---|---|",
  ]
  first = next(iter(runs.values())).splits
  for model in (m for m in first[splits[0]] if m in PC_MODELS):
    for split in splits:
      mean = lambda k: float(np.mean([value(r.splits[split][model], k) for r in runs.values()]))
      lines.append(
          f"| {predictive.TITLES.get(model, model)} | {split} | "
          + " | ".join(
              _fmt(mean(k)) for k in ("pc_cover", "pc_size", "pc_cal_cover", "pc_cal_size")
          )
          + " |"
      )
  return "\n".join(lines) + "\n"


def online_table(runs: dict, splits) -> str:
  """Coverage of the online 90 % regions (`conformal.online_levels`) at 1..5 s, lowest and
  highest over seeds, and their mean area at 5 s beside the split-conformal one."""
  h = regions.HORIZONS_S
  lines = [
      "| model | split | "
      + " | ".join(f"online {s} s" for s in h)
      + " | area 5 s cal / online [m^2] |",
      "|---|---|" + "---|" * (len(h) + 1),
  ]
  first = next(iter(runs.values())).splits
  for model in (m for m in first[splits[0]] if m != "meta"):
    for split in splits:
      if "online_cover_5s" not in first[split][model]:
        continue
      per_seed = lambda k: [value(r.splits[split][model], k) for r in runs.values()]
      span = lambda k: "-".join(
          dict.fromkeys(_fmt(v, "{:.3f}") for v in (min(per_seed(k)), max(per_seed(k))))
      )
      areas = " / ".join(
          _fmt(float(np.mean(per_seed(k))), "{:.1f}") for k in ("cal_area_5s", "online_area_5s")
      )
      lines.append(
          f"| {predictive.TITLES.get(model, model)} | {split} | "
          + " | ".join(span(f"online_cover_{s}s") for s in h)
          + f" | {areas} |"
      )
  return "\n".join(lines) + "\n"
