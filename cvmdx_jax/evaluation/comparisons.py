"""The paired comparisons of a report: cVMDx against every baseline on the same scenarios,
each a difference with its 95 % vehicle-bootstrap interval (`intervals`).

Rows (those whose two methods are in the report):
- the energy score (m) of each distribution: cVMDx's N samples (`cvmdx_mean`) and its K
  hypotheses with p(c) (`cvmdx_best_of_k`) against the point masses (`cv`, `ca`), the WTA
  MLP's heads with their p (`mlp_best_of_k`) and the MDN (`mdn_mean`);
- the K-sets: minADE_K, minFDE_K and Brier-minFDE of cVMDx's hypotheses against the
  learned baselines' heads / modes;
- the mean trajectory's ADE and FDE against each baseline's, per subset.
"""

import numpy as np

from cvmdx_jax import constants
from cvmdx_jax.evaluation import intervals

SUBSETS = ("all",) + constants.CLASS_NAMES
_DISTRIBUTIONS = ("cv", "ca", "mlp_best_of_k", "mdn_mean")
_K_SETS = ("mlp_best_of_k", "mdn_best_of_k")
_MEANS = ("cv", "ca", "mlp_mean", "mdn_mean")


def planned(methods) -> list:
  """(a, b, metric, subset) of every comparison whose methods are in `methods`."""
  rows = [
      (a, b, "energy_score", "all")
      for a in ("cvmdx_mean", "cvmdx_best_of_k")
      for b in _DISTRIBUTIONS
  ]
  rows += [
      ("cvmdx_best_of_k", b, m, "all") for b in _K_SETS for m in ("ade", "fde", "brier_min_fde")
  ]
  rows += [("cvmdx_mean", b, m, s) for b in _MEANS for m in ("ade", "fde") for s in SUBSETS]
  return [r for r in rows if r[0] in methods and r[1] in methods]


def paired(errors: dict, recording_id, track_id, labels, seed: int = 0) -> list:
  """Every `planned` comparison over the per-scenario errors {method: {metric: (M,)}}:
  [{"a", "b", "metric", "subset", "by_seed": {"": paired_difference}}] (subsets without
  scenarios left out)."""
  labels = np.asarray(labels)
  out = []
  for a, b, metric, subset in planned(errors):
    if metric not in errors[a] or metric not in errors[b]:
      continue
    sel = np.ones(len(labels), bool) if subset == "all" else labels == SUBSETS.index(subset) - 1
    if not sel.any():
      continue
    groups = intervals.vehicle_groups(np.asarray(recording_id)[sel], np.asarray(track_id)[sel])
    row = intervals.paired_difference(
        np.asarray(errors[a][metric])[sel], np.asarray(errors[b][metric])[sel], groups, seed=seed
    )
    out.append({"a": a, "b": b, "metric": metric, "subset": subset, "by_seed": {"": row}})
  return out


def markdown(rows: list) -> str:
  """The comparisons as a table: 'difference [low, high] verdict' (a - b; "better": a is
  lower with the interval below 0)."""
  lines = [
      "| a - b | metric | subset | difference [95 % interval, vehicles resampled] |",
      "|---|---|---|---|",
  ]
  for r in rows:
    lines.append(
        f"| {r['a']} - {r['b']} | {r['metric']} | {r['subset']} | "
        f"{intervals.format_difference(r['by_seed'][''])} |"
    )
  return "\n".join(lines) + "\n"
