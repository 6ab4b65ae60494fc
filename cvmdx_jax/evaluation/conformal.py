"""Split-conformal calibration on val of the prediction regions and of p(c).

Regions: a scenario's conformity score is u, the mass of the smallest highest-density
region holding the truth (`regions.hdr`). For a nominal level a, the calibrated level is
the ceil((n + 1) a)-th smallest of the n val scores (`calibrated_level`); the test region
of that level holds the truth with probability >= a for exchangeable scenarios (Vovk et
al. 2005; Angelopoulos and Bates 2021). With delta: the same per tercile of the scenario's
uncertainty delta (edges from val; Mondrian conformal), so that uncertain scenarios get
larger regions and certain ones smaller at the same coverage (`delta_levels`).

p(c): a set of hypotheses taken in order of decreasing p until their cumulative p
reaches a threshold; its score is the cumulative p up to and including the hypothesis
closest to the truth at 5 s (`hypothesis_scores`); the threshold is calibrated on val
like a level (adaptive prediction sets, Romano et al. 2020).
"""

import math

import numpy as np

DELTA_BINS = 3  # terciles of delta


def calibrated_level(val_scores, level: float) -> float:
  """The ceil((n + 1) level)-th smallest of n val scores (1.0 where that exceeds n)."""
  scores = np.sort(np.asarray(val_scores, np.float64))
  rank = math.ceil((len(scores) + 1) * level)
  return 1.0 if rank > len(scores) else float(scores[rank - 1])


def delta_edges(val_delta, bins: int = DELTA_BINS) -> np.ndarray:
  """Inner quantile edges (bins - 1,) of val's delta."""
  return np.quantile(np.asarray(val_delta, np.float64), np.arange(1, bins) / bins)


def delta_levels(val_scores, val_delta, delta, levels, bins: int = DELTA_BINS) -> np.ndarray:
  """Calibrated levels per scenario (M, L): each scenario takes those of its delta bin,
  calibrated on the val scenarios of that bin."""
  edges = delta_edges(val_delta, bins)
  val_bin = np.digitize(np.asarray(val_delta), edges)
  table = np.array(
      [
          [calibrated_level(np.asarray(val_scores)[val_bin == b], a) for a in levels]
          for b in range(bins)
      ]
  )
  return table[np.digitize(np.asarray(delta), edges)]


def hypothesis_scores(probs, closest) -> np.ndarray:
  """Cumulative p of the hypotheses (by decreasing p) up to and including the closest one.

  probs (M, K) (0 = unused slot), closest (M,) int index -> (M,).
  """
  probs = np.asarray(probs, np.float64)
  order = np.argsort(-probs, axis=1, kind="stable")
  cum = np.cumsum(np.take_along_axis(probs, order, axis=1), axis=1)
  rank = np.argmax(order == np.asarray(closest)[:, None], axis=1)
  return cum[np.arange(len(rank)), rank]


def hypothesis_set_size(probs, threshold: float) -> np.ndarray:
  """Hypotheses in each set: the fewest (by decreasing p) whose cumulative p reaches
  threshold, all used ones at most. probs (M, K) -> (M,) int."""
  probs = np.asarray(probs, np.float64)
  cum = np.cumsum(-np.sort(-probs, axis=1), axis=1)
  used = np.sum(probs > 0, axis=1)
  return np.minimum(np.sum(cum < threshold - 1e-12, axis=1) + 1, used)
