"""Figures: multimodal predictions (paper Fig. 1), KL vs codebook usage (Fig. 3) and the
reliability diagram of the hypothesis probabilities, as PNG bytes (the report writes them
with its other files as one group)."""

import io

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from scipy import optimize  # noqa: E402

from cvmdx_jax import constants  # noqa: E402

LANE_WIDTH_M = 3.5
_COLOURS = ("tab:blue", "tab:orange", "tab:green")


def _png(fig) -> bytes:
  """`fig` rendered as PNG at 110 dpi; the figure is closed."""
  buffer = io.BytesIO()
  fig.tight_layout()
  fig.savefig(buffer, format="png", dpi=110)
  plt.close(fig)
  return buffer.getvalue()


def plot_predictions(scenarios, output, indices) -> bytes:
  """One panel per scenario: lane lines (3.5 m lanes, ego lane centred at y = 0 at
  t0), observed ego and neighbours, samples coloured by hypothesis, hypothesis means
  with p(c), the mean trajectory and the ground truth.

  Args:
    scenarios: `Scenarios`.
    output: `PredictorOutput` for the same scenarios.
    indices: scenario indices to draw.

  Returns:
    The PNG file's bytes.
  """
  indices = list(indices)
  cols = min(3, len(indices))
  rows = -(-len(indices) // cols)
  fig, axes = plt.subplots(rows, cols, figsize=(6 * cols, 2.6 * rows), squeeze=False)
  pred, hyp = output.prediction, output.hypotheses
  for ax, i in zip(axes.flat, indices):
    for k in (-2.5, -1.5, -0.5, 0.5, 1.5, 2.5):
      ax.axhline(k * LANE_WIDTH_M, color="0.7", lw=0.8, ls="--" if abs(k) < 2 else "-")
    for slot in range(1, constants.NUM_VEHICLES):
      m = scenarios.mask[i, slot]
      if m.any():
        ax.plot(scenarios.xi[i, slot, m, 0], scenarios.xi[i, slot, m, 1], color="0.5", lw=1)
    ax.plot(scenarios.xi[i, 0, :, 0], scenarios.xi[i, 0, :, 1], color="k", lw=1.5, label="observed")
    for n in range(pred.trajectories.shape[1]):
      c = _COLOURS[int(hyp.labels[i, n]) % len(_COLOURS)]
      ax.plot(
          pred.trajectories[i, n, :, 0], pred.trajectories[i, n, :, 1], color=c, lw=0.6, alpha=0.6
      )
    for c in range(hyp.means.shape[1]):
      if hyp.probs[i, c] > 0:
        ax.plot(
            hyp.means[i, c, :, 0],
            hyp.means[i, c, :, 1],
            color=_COLOURS[c],
            lw=2.2,
            label=f"hypothesis p={hyp.probs[i, c]:.2f}",
        )
    ax.plot(pred.mean[i, :, 0], pred.mean[i, :, 1], color="m", lw=1.2, ls=":", label="mean")
    ax.plot(
        scenarios.future[i, :, 0],
        scenarios.future[i, :, 1],
        color="r",
        lw=1.5,
        ls="--",
        label="ground truth",
    )
    ax.set_title(
        f"#{i} {constants.CLASS_NAMES[int(scenarios.label[i])]}  q={int(output.q[i])}"
        f"  delta={float(output.delta[i]):.1f}",
        fontsize=9,
    )
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_ylim(-3 * LANE_WIDTH_M, 3 * LANE_WIDTH_M)
    ax.legend(fontsize=6, loc="upper left")
  for ax in axes.flat[len(indices) :]:
    ax.axis("off")
  return _png(fig)


def power_law_fit(usage, kl):
  """Fits kl = a * usage^(-b) + c; returns (a, b, c) or None if it cannot be fitted."""
  if len(usage) < 4:
    return None
  f = lambda n, a, b, c: a * np.power(n, -b) + c
  try:
    params, _ = optimize.curve_fit(f, usage, kl, p0=(1.0, 0.6, 0.05), maxfev=20000)
  except (RuntimeError, ValueError):
    return None
  return tuple(float(p) for p in params)


def plot_kl_vs_usage(token_kl, title: str = "") -> tuple[bytes, tuple | None]:
  """KL(p_q || p_theta,q) against N_q (log x) with the power-law fit; returns (PNG bytes,
  the fit (a, b, c) or None)."""
  fit = power_law_fit(token_kl.usage, token_kl.kl)
  fig, ax = plt.subplots(figsize=(5, 3.5))
  ax.scatter(token_kl.usage, token_kl.kl, s=14, label="codebook entries")
  if fit is not None:
    n = np.geomspace(max(token_kl.usage.min(), 1), token_kl.usage.max(), 100)
    ax.plot(
        n,
        fit[0] * n ** -fit[1] + fit[2],
        color="r",
        label=f"{fit[0]:.2f} N^-{fit[1]:.2f} + {fit[2]:.2f}",
    )
  ax.set_xscale("log")
  ax.set_xlabel("N_q (training scenarios with token q)")
  ax.set_ylabel("KL(p_q || p_theta,q) [nats]")
  ax.set_title(title, fontsize=9)
  ax.legend(fontsize=7)
  return _png(fig), fit


def plot_reliability(diagram: dict, title: str = "") -> bytes:
  """Reliability diagram: per probability bin, the share of hypotheses that were the
  closest to the truth against their mean probability (`scoring.calibration`'s
  diagram: lists "count", "confidence", "accuracy"), with the hypothesis count per bin;
  returns the PNG bytes."""
  count = np.asarray(diagram["count"], np.float64)
  conf, acc = (np.asarray(diagram[k], np.float64) for k in ("confidence", "accuracy"))
  edges = np.linspace(0.0, 1.0, len(count) + 1)
  used = count > 0
  fig, (ax, bars) = plt.subplots(
      2, 1, figsize=(4.5, 5), sharex=True, gridspec_kw={"height_ratios": (3, 1)}
  )
  ax.plot([0, 1], [0, 1], color="0.6", ls="--", lw=1, label="calibrated")
  ax.plot(conf[used], acc[used], marker="o", color="tab:blue", label="hypotheses")
  ax.set_ylabel("share closest to the truth")
  ax.set_xlim(0, 1)
  ax.set_ylim(0, 1)
  ax.set_title(title, fontsize=9)
  ax.legend(fontsize=7, loc="upper left")
  bars.bar(edges[:-1], count, width=np.diff(edges), align="edge", color="tab:blue", alpha=0.6)
  bars.set_xlabel("hypothesis probability p(c)")
  bars.set_ylabel("count")
  return _png(fig)


def plot_region_reliability(u_by_model: dict, horizons, title: str = "") -> bytes:
  """Reliability of the highest-density prediction regions: one panel per horizon, per
  model the share of true positions inside the level-a region against a.

  u_by_model: {model: {horizon s: (M,) u}} (`regions.hdr`: the truth lies in the level-a
  region iff u <= a). Returns the PNG bytes.
  """
  levels = np.linspace(0.0, 1.0, 41)
  fig, axes = plt.subplots(1, len(horizons), figsize=(3.0 * len(horizons), 3.2), sharey=True)
  for ax, s in zip(np.atleast_1d(axes), horizons):
    ax.plot([0, 1], [0, 1], color="0.6", ls="--", lw=1)
    for model, by_horizon in u_by_model.items():
      u = np.asarray(by_horizon[s])
      ax.plot(levels, [np.mean(u <= a) for a in levels], lw=1.2, label=model)
    ax.set_title(f"{s} s", fontsize=9)
    ax.set_xlabel("nominal mass a")
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1)
  np.atleast_1d(axes)[0].set_ylabel("share of true positions inside")
  np.atleast_1d(axes)[0].legend(fontsize=6, loc="upper left")
  fig.suptitle(title, fontsize=9)
  return _png(fig)
