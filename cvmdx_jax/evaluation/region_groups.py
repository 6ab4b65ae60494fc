"""Calibrated regions across recordings: which covariate of t0, if any, to group them by.

Split conformal covers the nominal level over scenarios exchangeable with the calibration
ones. The scenarios of one recording share its traffic and drivers, so a new recording's
coverage varies around the pooled one by more than the scenarios' sampling noise. A
Mondrian grouping (levels per tercile of a covariate, `conformal.mondrian_levels`) helps on
a recording never calibrated on only if the covariate carries what differs between
recordings. `leave_one_out` checks that on the calibration recordings themselves: calibrate
on all but one, cover the one left out.
"""

import numpy as np

from cvmdx_jax.evaluation import conformal

COVARIATES = ("delta", "v0", "neighbours", "neighbour_speed", "lateral_spread")


def covariates(scenarios, output) -> dict:
  """Per scenario (M,) what is known at t0: the uncertainty delta, the ego speed v0 (m/s),
  the neighbour slots occupied at t0, their mean speed (m/s; v0 where none), and the
  lateral spread (std, m) of the N samples at the last step."""
  mask = np.asarray(scenarios.mask)[:, 1:, -1]
  vel = np.asarray(scenarios.xi)[:, 1:, -1, 2:]
  count = mask.sum(axis=1)
  speed = np.hypot(vel[..., 0], vel[..., 1])
  v0 = np.asarray(scenarios.v0, np.float64)
  samples = np.asarray(output.prediction.trajectories)
  return {
      "delta": np.asarray(output.delta, np.float64),
      "v0": v0,
      "neighbours": count.astype(np.float64),
      "neighbour_speed": np.where(count > 0, (speed * mask).sum(axis=1) / np.maximum(count, 1), v0),
      "lateral_spread": samples[:, :, -1, 1].std(axis=1).astype(np.float64),
  }


def leave_one_out(u, recordings, x=None, level: float = 0.9, bins: int = conformal.DELTA_BINS):
  """Coverage of each recording by levels calibrated on the others.

  Args:
    u: (M, H) conformity scores per horizon (`regions.hdr`'s u).
    recordings: (M,) recording of each scenario.
    x: (M,) covariate for per-bin levels, or None for one level (plain).
    level: nominal coverage.
    bins: quantile bins of x (edges from the other recordings).

  Returns:
    ids (R,), counts (R,) scenarios per recording, coverage (R, H).
  """
  u, recordings = np.asarray(u), np.asarray(recordings)
  ids, counts = np.unique(recordings, return_counts=True)
  if len(ids) < 2:
    raise ValueError(f"leave_one_out needs scenarios of 2 recordings or more, got {len(ids)}")
  cover = np.empty((len(ids), u.shape[1]))
  for r, rec in enumerate(ids):
    out = recordings == rec
    for h in range(u.shape[1]):
      if x is None:
        lv = conformal.calibrated_level(u[~out, h], level)
      else:
        lv = conformal.mondrian_levels(u[~out, h], x[~out], x[out], (level,), bins)[:, 0]
      cover[r, h] = np.mean(u[out, h] <= lv)
  return ids, counts, cover


def errors(counts, cover, level: float = 0.9) -> tuple[float, float]:
  """(mean, largest) |coverage - level|: the mean weighted by each recording's scenarios
  and taken over horizons."""
  err = np.abs(np.asarray(cover) - level)
  weights = np.asarray(counts, np.float64)
  return float(np.sum(weights[:, None] * err) / (weights.sum() * err.shape[1])), float(err.max())


def recording_coverage(cover, recordings) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
  """A report's per scenario covered flags (M,) -> ids (R,), counts (R,), coverage (R,)."""
  recordings = np.asarray(recordings)
  ids, inverse, counts = np.unique(recordings, return_inverse=True, return_counts=True)
  return ids, counts, np.bincount(inverse, weights=np.asarray(cover, np.float64)) / counts
