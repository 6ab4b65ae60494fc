"""Evaluation like the paper: cVMDx (mean, most likely p(c), best of K) against
constant velocity, constant acceleration + yaw rate and a single DDPM sample (cVMD),
overall and per maneuver class, as nested dicts and markdown tables.

Metrics per method and subset: `ade`, `fde` (m), `miss_rate` (final error > 2 m;
for best-of-K: the best hypothesis), `hit_rate` (final lateral error < 1.75 m; for
best-of-K: any hypothesis), `num_scenarios`.
"""

import dataclasses

import jax.numpy as jnp
import numpy as np

from cvmdx_jax import constants, metrics
from cvmdx_jax.evaluation import baselines

METHODS = ("cvmdx_mean", "cvmdx_most_likely", "cvmdx_best_of_k", "cv", "ca", "ddpm_single")
SUBSETS = ("all",) + constants.CLASS_NAMES
METHOD_TITLES = {
    "cvmdx_mean": "cVMDx mean of N", "cvmdx_most_likely": "cVMDx most likely p(c)",
    "cvmdx_best_of_k": "cVMDx best of K (minADE_K / minFDE_K)", "cv": "Constant velocity",
    "ca": "Constant acceleration + yaw rate", "ddpm_single": "cVMD-style single DDPM sample",
}
# Paper, Table II (highD): ADE / FDE@5s in metres.
PAPER_HIGHD = {"cvmdx_mean": (1.37, 3.84), "cvmdx_most_likely": (1.43, 4.00),
               "cvmdx_best_of_k": (1.33, 3.68), "ddpm_single": (1.79, 3.76)}


def single_trajectory_errors(pred, gt) -> dict:
  """Per-scenario errors of one trajectory per scenario: (M, T, 2) each -> dict of (M,)."""
  final = metrics.fde(pred, gt)
  return {"ade": metrics.ade(pred, gt), "fde": final, "miss_rate": metrics.miss(final),
          "hit_rate": metrics.hit(pred, gt)}


def best_of_k_errors(hyps, probs, gt) -> dict:
  """Per-scenario best-of-K errors over the used hypothesis slots."""
  valid = probs > 0
  final = metrics.min_fde_k(hyps, gt, valid)
  hits = jnp.where(valid, metrics.hit(hyps, gt[:, None]), 0.0)
  return {"ade": metrics.min_ade_k(hyps, gt, valid), "fde": final,
          "miss_rate": metrics.miss(final), "hit_rate": jnp.max(hits, axis=-1)}


def cvmdx_errors(prediction, gt) -> dict:
  """The three cVMDx read-outs of a `Prediction` -> {method: per-scenario errors}."""
  hyp = prediction.hypotheses
  return {
      "cvmdx_mean": single_trajectory_errors(prediction.mean, gt),
      "cvmdx_most_likely": single_trajectory_errors(
          metrics.most_likely(hyp.means, hyp.probs), gt),
      "cvmdx_best_of_k": best_of_k_errors(hyp.means, hyp.probs, gt),
  }


def baseline_errors(scenarios) -> dict:
  """Constant velocity and constant acceleration + yaw rate."""
  gt = jnp.asarray(scenarios.future)
  return {"cv": single_trajectory_errors(baselines.constant_velocity(scenarios.xi), gt),
          "ca": single_trajectory_errors(
              baselines.constant_acceleration_yaw_rate(scenarios.xi), gt)}


def summarise(errors: dict, labels) -> dict:
  """{method: per-scenario errors} + labels (M,) -> {method: {subset: {metric: value}}}."""
  labels = np.asarray(labels)
  out = {}
  for method, per in errors.items():
    per = {k: np.asarray(v, np.float64) for k, v in per.items()}
    out[method] = {}
    for subset in SUBSETS:
      sel = (np.ones_like(labels, bool) if subset == "all"
             else labels == SUBSETS.index(subset) - 1)
      row = {k: float(v[sel].mean()) if sel.any() else float("nan") for k, v in per.items()}
      out[method][subset] = {**row, "num_scenarios": int(sel.sum())}
  return out


def markdown_tables(results: dict) -> str:
  """Two markdown tables: overall (paper Table II layout) and per class (Table I)."""
  fmt = lambda x: "n/a" if x != x else f"{x:.2f}"
  lines = ["| model | ADE [m] | FDE@5s [m] | miss rate (2 m) | hit rate (1.75 m) | scenarios "
           "| paper highD ADE / FDE |", "|---|---|---|---|---|---|---|"]
  for method, by_subset in results.items():
    r = by_subset["all"]
    paper = PAPER_HIGHD.get(method)
    lines.append(f"| {METHOD_TITLES.get(method, method)} | {fmt(r['ade'])} | {fmt(r['fde'])} | "
                 f"{fmt(r['miss_rate'])} | {fmt(r['hit_rate'])} | {r['num_scenarios']} | "
                 f"{'%.2f / %.2f' % paper if paper else '-'} |")
  lines += ["", "| model | " + " | ".join(f"{s} ADE | {s} FDE" for s in constants.CLASS_NAMES)
            + " |", "|---|" + "---|---|" * len(constants.CLASS_NAMES)]
  for method, by_subset in results.items():
    cells = " | ".join(f"{fmt(by_subset[s]['ade'])} | {fmt(by_subset[s]['fde'])}"
                       for s in constants.CLASS_NAMES)
    lines.append(f"| {METHOD_TITLES.get(method, method)} | {cells} |")
  return "\n".join(lines) + "\n"


def gaussian_kl(mu_p, cov_p, mu_q, cov_q) -> float:
  """KL(N(mu_p, cov_p) || N(mu_q, cov_q)) in nats (closed form)."""
  d = len(mu_p)
  inv_q = np.linalg.inv(cov_q)
  diff = mu_q - mu_p
  return 0.5 * float(np.trace(inv_q @ cov_p) + diff @ inv_q @ diff - d
                     + np.linalg.slogdet(cov_q)[1] - np.linalg.slogdet(cov_p)[1])


@dataclasses.dataclass(frozen=True)
class TokenKL:
  """Per codebook entry: training usage N_q and KL(p_q(Y) || p_theta,q(Y))."""

  token: np.ndarray
  usage: np.ndarray
  kl: np.ndarray


def kl_per_token(q_test, future, samples, train_usage, min_members: int = 3,
                 ridge: float = 0.25) -> TokenKL:
  """KL between the data and model distributions of the 5 s position per token.

  p_q: Gaussian of the ground-truth final positions of the test scenarios with token
  q; p_theta,q: Gaussian of all model samples' final positions for those scenarios.
  A ridge (m^2) keeps tiny clusters' covariances invertible.

  Args:
    q_test: (M,) test tokens; future: (M, T, 2); samples: (M, N, T, 2);
    train_usage: (Q,) training scenarios per token (N_q).
  """
  rows = []
  for token in np.unique(q_test):
    sel = q_test == token
    if sel.sum() < min_members or train_usage[token] == 0:
      continue
    data = np.asarray(future)[sel, -1]
    model = np.asarray(samples)[sel, :, -1].reshape(-1, 2)
    eye = ridge * np.eye(2)
    rows.append((token, train_usage[token],
                 gaussian_kl(data.mean(0), np.cov(data.T) + eye, model.mean(0),
                             np.cov(model.T) + eye)))
  arr = np.array(rows, np.float64).reshape(-1, 3)
  return TokenKL(token=arr[:, 0].astype(int), usage=arr[:, 1], kl=arr[:, 2])
