"""Paired differences of two models' per-scenario scores with vehicle-bootstrap intervals.

Windows of one vehicle (the same (recording_id, track_id)) are not independent, so the
bootstrap resamples whole vehicles: each of `DRAWS` replicates draws as many vehicles as
there are, with replacement, and takes all their scenarios. The interval is the 2.5 / 97.5
percentile of the replicated difference (95 %). A comparison says "better" (or "worse")
only where the interval excludes 0; otherwise "tie".
"""

import numpy as np

DRAWS = 2000
CONFIDENCE = 0.95


def vehicle_groups(recording_id, track_id) -> np.ndarray:
  """(M,) int group of each scenario: one per (recording_id, track_id)."""
  pairs = np.stack([np.asarray(recording_id, np.int64), np.asarray(track_id, np.int64)], 1)
  return np.unique(pairs, axis=0, return_inverse=True)[1].reshape(-1)


def _statistic(sums, sq_sums, counts, kind: str):
  if kind == "mean":
    return sums / counts
  if kind == "rmse":
    return np.sqrt(sq_sums / counts)
  raise ValueError(f"unknown statistic {kind!r} (mean or rmse)")


def paired_difference(a, b, groups, seed: int = 0, kind: str = "mean", draws: int = DRAWS) -> dict:
  """stat(a) - stat(b) over the same scenarios, with its vehicle-bootstrap interval.

  Args:
    a, b: (M,) per-scenario values of the two models (for kind "rmse": errors, m).
    groups: (M,) int vehicle of each scenario (`vehicle_groups`).
    seed: bootstrap draw.
    kind: "mean" (mean of the values) or "rmse" (root of the mean of their squares).

  Returns:
    {"a", "b", "difference", "low", "high", "verdict"} with verdict "better" (a lower,
    interval below 0), "worse" (above 0) or "tie"; "relative", "relative_low",
    "relative_high": stat(a) / stat(b) - 1 and its interval from the same replicates
    (NaN where stat(b) is 0).
  """
  a, b, groups = np.asarray(a, np.float64), np.asarray(b, np.float64), np.asarray(groups)
  n_groups = int(groups.max()) + 1
  per_group = lambda v: np.bincount(groups, v, minlength=n_groups)
  counts = per_group(np.ones_like(a))
  sums = np.stack([per_group(a), per_group(b)])  # (2, G)
  sq_sums = np.stack([per_group(a * a), per_group(b * b)])
  rng = np.random.default_rng(seed)
  picks = rng.integers(0, n_groups, size=(draws, n_groups))
  weight = np.stack([np.bincount(row, minlength=n_groups) for row in picks]).astype(np.float64)
  stat = lambda w: _statistic(w @ sums.T, w @ sq_sums.T, (w @ counts)[:, None], kind)
  replicated = stat(weight)
  point = stat(np.ones((1, n_groups)))[0]
  tail = 100.0 * (1.0 - CONFIDENCE) / 2.0
  low, high = np.percentile(replicated[:, 0] - replicated[:, 1], [tail, 100.0 - tail])
  with np.errstate(divide="ignore", invalid="ignore"):
    ratios = replicated[:, 0] / replicated[:, 1] - 1.0
    relative = point[0] / point[1] - 1.0 if point[1] else np.nan
  rel_low, rel_high = np.percentile(ratios, [tail, 100.0 - tail]) if point[1] else (np.nan,) * 2
  verdict = "better" if high < 0 else "worse" if low > 0 else "tie"
  return {
      "a": float(point[0]),
      "b": float(point[1]),
      "difference": float(point[0] - point[1]),
      "low": float(low),
      "high": float(high),
      "verdict": verdict,
      "relative": float(relative),
      "relative_low": float(rel_low),
      "relative_high": float(rel_high),
  }


def format_difference(row: dict, spec: str = "{:+.3f}") -> str:
  """'-0.102 [-0.151, -0.053] better' of a `paired_difference` row."""
  return (
      f"{spec.format(row['difference'])} [{spec.format(row['low'])}, "
      f"{spec.format(row['high'])}] {row['verdict']}"
  )
