"""The hypothesis sweep's rules (`experiments/hypothesis_sweep.py`): method specs, the
choice of the default method and N, and its table.

A row is one (method, N) setting's means over a split: COLUMNS, "single_mode_share",
"predict_s" (seconds per scenario of the whole prediction) and "hypotheses_s" (seconds per
scenario of the hypothesis step alone).
"""

import dataclasses

from cvmdx_jax.config.sampling import HypothesisConfig
from cvmdx_jax.errors import UserError

COLUMNS = (
    "mean_ade",
    "mean_fde",
    "min_ade_k",
    "min_fde_k",
    "brier_min_fde",
    "energy_score",
    "nll_final",
    "ece",
)


def hypothesis_config(spec: str, base: HypothesisConfig) -> HypothesisConfig:
  """'bic' or 'kmeans:<endpoint_weight>' -> the run's `HypothesisConfig` with that method."""
  method, _, weight = spec.partition(":")
  if method == "bic" and not weight:
    return dataclasses.replace(base, method="bic")
  if method == "kmeans":
    return dataclasses.replace(base, method="kmeans", endpoint_weight=float(weight or 0.0))
  raise UserError(f"hypothesis method {spec!r} is not 'bic' or 'kmeans:<endpoint_weight>'")


def choose_hypotheses(
    rows: list[dict], reference: dict, tolerance: float, max_num_samples: int = 0
) -> dict:
  """The lowest Brier-minFDE among rows with num_samples <= max_num_samples (0 = any)
  whose mean ADE is <= (1 + tolerance) x the reference row's."""
  ok = [
      r
      for r in rows
      if r["mean_ade"] <= (1.0 + tolerance) * reference["mean_ade"]
      and (not max_num_samples or r["num_samples"] <= max_num_samples)
  ]
  return min(ok, key=lambda r: (r["brier_min_fde"], r["num_samples"]))


def hypotheses_table(
    rows: list[dict], choice: dict, note: str, tolerance: float, max_num_samples: int = 0
) -> str:
  """One row per (method, N), the chosen one marked."""
  lines = [
      f"Hypothesis sweep: {note}",
      "",
      "| method | N | mean ADE | mean FDE | minADE_K | minFDE_K | Brier-minFDE | energy "
      "score | NLL 5 s | ECE | single-mode share | predict s / scenario | hypotheses "
      "ms / scenario |",
      "|" + "---|" * 13,
  ]
  for r in rows:
    mark = " **(chosen)**" if r is choice else ""
    lines.append(
        f"| {r['method']}{mark} | {r['num_samples']} | "
        + " | ".join(f"{r[c]:.3f}" for c in COLUMNS)
        + f" | {r['single_mode_share']:.2f} | {r['predict_s']:.4f} | "
        f"{1e3 * r['hypotheses_s']:.3f} |"
    )
  bound = f" among N <= {max_num_samples}" if max_num_samples else ""
  lines += [
      "",
      f"Chosen: {choice['method']} with N = {choice['num_samples']}, the lowest "
      f"Brier-minFDE{bound} whose mean ADE is within {100 * tolerance:g} % of the "
      "reference's (chosen on val).",
  ]
  return "\n".join(lines) + "\n"
