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

Online (`online_levels`): split conformal holds only where test scenarios are exchangeable
with the calibration ones, which a road no calibration recording has breaks. A stream
learns each truth h seconds after its prediction; adaptive conformal inference (Gibbs and
Candes 2021) moves the level with each miss that has arrived, L <- L + gamma (miss - (1 -
a)), from the split-conformal level. Its long-run miss rate is within (max(a_1, 1 - a_1) +
gamma) / (gamma T) of 1 - a over any T scenarios, whatever the road (feedback without
delay); `aci_gamma` takes the gamma that makes this bound `ACI_TOLERANCE`.
"""

import math

import numpy as np

DELTA_BINS = 3  # terciles of delta
ACI_TOLERANCE = 0.02  # long-run coverage error that `aci_gamma`'s step guarantees
LEVEL_CAP = 0.999  # largest region mass an online level takes (1 = the whole plane)


def calibrated_level(val_scores, level: float) -> float:
  """The ceil((n + 1) level)-th smallest of n val scores (1.0 where that exceeds n)."""
  scores = np.sort(np.asarray(val_scores, np.float64))
  rank = math.ceil((len(scores) + 1) * level)
  return 1.0 if rank > len(scores) else float(scores[rank - 1])


def bin_edges(val_x, bins: int = DELTA_BINS) -> np.ndarray:
  """Inner quantile edges (bins - 1,) of a covariate on val (delta in the reports)."""
  return np.quantile(np.asarray(val_x, np.float64), np.arange(1, bins) / bins)


def mondrian_levels(val_scores, val_x, x, levels, bins: int = DELTA_BINS) -> np.ndarray:
  """Calibrated levels per scenario (M, L): each scenario takes those of its bin of the
  covariate x (quantile bins of val_x), calibrated on the val scenarios of that bin (1.0
  for a bin without val scenarios)."""
  edges = bin_edges(val_x, bins)
  val_bin = np.digitize(np.asarray(val_x), edges)
  table = np.array(
      [
          [calibrated_level(np.asarray(val_scores)[val_bin == b], a) for a in levels]
          for b in range(bins)
      ]
  )
  return table[np.digitize(np.asarray(x), edges)]


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


def aci_gamma(start_level: float, count: int, tolerance: float = ACI_TOLERANCE) -> float:
  """Step gamma with Gibbs and Candes' bound (max(a_1, 1 - a_1) + gamma) / (gamma T) equal
  to tolerance over T = count scenarios, a_1 = 1 - start_level."""
  if tolerance * count <= 1.0:
    raise ValueError(f"aci_gamma: {count} scenarios cannot bound the coverage to {tolerance}")
  miss = 1.0 - start_level
  return max(miss, 1.0 - miss) / (tolerance * count - 1.0)


def online_levels(u, times, delay, start: float, level: float, gamma: float) -> np.ndarray:
  """Levels of adaptive conformal inference over a stream with delayed truths.

  Scenarios are taken by time (ties in the given order); the miss of scenario i (u_i above
  its level) arrives at times_i + delay and moves the level of every later scenario by
  gamma (miss - (1 - level)). Regions use the level clipped to [0, LEVEL_CAP].

  Args:
    u: (M,) conformity scores (`regions.hdr`'s u; covered where u <= level).
    times: (M,) when each prediction is made (any unit; recordings one after another).
    delay: how long after its prediction a scenario's truth is known, in the unit of times.
    start: the first level (split-conformal on the calibration set).
    level: the nominal coverage a.
    gamma: step size (`aci_gamma`).

  Returns:
    (M,) the level of each scenario, in the input's order.
  """
  u = np.asarray(u, np.float64)
  order = np.argsort(np.asarray(times), kind="stable")
  t, u = np.asarray(times, np.float64)[order], u[order]
  state, arrived = float(start), 0
  used = np.empty(len(u))
  for j in range(len(u)):
    while arrived < j and t[arrived] + delay <= t[j]:
      state += gamma * (float(u[arrived] > used[arrived]) - (1.0 - level))
      arrived += 1
    used[j] = min(max(state, 0.0), LEVEL_CAP)
  out = np.empty_like(used)
  out[order] = used
  return out
