"""The markdown tables of an evaluation report: overall (the paper's Table II layout plus
the added metrics), per class (Table I), cVMDx's scenario uncertainty and its probabilistic
quality, from `scoring.summarise`'s {method: {subset: {metric: value}}}."""

from cvmdx_jax import constants
from cvmdx_jax.evaluation.scoring import SUBSETS

METHOD_TITLES = {
    "cvmdx_mean": "cVMDx mean of N",
    "cvmdx_most_likely": "cVMDx most likely p(c)",
    "cvmdx_best_of_k": "cVMDx best of K (minADE_K / minFDE_K)",
    "cv": "Constant velocity",
    "ca": "Constant acceleration + yaw rate",
    "ddpm_single": "cVMD-style single DDPM sample",
    # the learned baseline (`learned_baseline`), in reports given a --baseline_dir
    "mlp_most_likely": "MLP, 3 heads (WTA): most likely",
    "mlp_mean": "MLP, 3 heads (WTA): probability-weighted mean",
    "mlp_best_of_k": "MLP, 3 heads (WTA): best of K",
    # the mixture density network (`mdn_rows`), given its run
    "mdn_mean": "MDN, 3 Gaussian modes: mixture mean",
    "mdn_best_of_k": "MDN, 3 Gaussian modes: best of K",
}
# Paper, Table II (highD): ADE / FDE@5s in metres.
PAPER_HIGHD = {
    "cvmdx_mean": (1.37, 3.84),
    "cvmdx_most_likely": (1.43, 4.00),
    "cvmdx_best_of_k": (1.33, 3.68),
    "ddpm_single": (1.79, 3.76),
}


def markdown_tables(results: dict) -> str:
  """Markdown tables: overall (paper Table II layout plus the added metrics), per class
  (Table I), and where cVMDx's rows are present its scenario uncertainty and probabilistic
  quality per subset."""
  fmt = lambda x, spec="{:.2f}": "-" if x is None else "n/a" if x != x else spec.format(x)
  lines = [
      "| model | ADE [m] | FDE@5s [m] | final lon [m] | final lat [m] | miss rate (2 m) "
      "| hit rate (1.75 m) | Brier-minFDE [m] | target lane, p >= 0.2 (lc) | scenarios "
      "| paper highD ADE / FDE |",
      "|---|---|---|---|---|---|---|---|---|---|---|",
  ]
  for method, by_subset in results.items():
    r = by_subset["all"]
    paper = PAPER_HIGHD.get(method)
    cells = " | ".join(
        fmt(r.get(k))
        for k in (
            "ade",
            "fde",
            "final_lon",
            "final_lat",
            "miss_rate",
            "hit_rate",
            "brier_min_fde",
            "target_lane_hit",
        )
    )
    lines.append(
        f"| {METHOD_TITLES.get(method, method)} | {cells} | {r['num_scenarios']} | "
        f"{f'{paper[0]:.2f} / {paper[1]:.2f}' if paper else '-'} |"
    )
  lines += [
      "",
      "| model | " + " | ".join(f"{s} ADE | {s} FDE" for s in constants.CLASS_NAMES) + " |",
      "|---|" + "---|---|" * len(constants.CLASS_NAMES),
  ]
  for method, by_subset in results.items():
    cells = " | ".join(
        f"{fmt(by_subset[s]['ade'])} | {fmt(by_subset[s]['fde'])}" for s in constants.CLASS_NAMES
    )
    lines.append(f"| {METHOD_TITLES.get(method, method)} | {cells} |")
  if "cvmdx_mean" in results:
    lines += [
        "",
        "| cVMDx scenario uncertainty | scenarios | out of distribution "
        "| Spearman rho(delta, mean-of-N ADE) | p-value |",
        "|---|---|---|---|---|",
    ]
    for subset in SUBSETS:
      r = results["cvmdx_mean"][subset]
      lines.append(
          f"| {subset} | {r['num_scenarios']} | "
          f"{fmt(r.get('out_of_distribution'), '{:.1%}')} | "
          f"{fmt(r.get('delta_ade_spearman'))} | "
          f"{fmt(r.get('delta_ade_spearman_p'), '{:.2g}')} |"
      )
  if "cvmdx_best_of_k" in results:
    lines += [
        "",
        "| cVMDx probabilistic quality | scenarios | energy score of N [m] "
        "| NLL at 5 s [nats] | ECE of p(c), 10 bins | Brier-minFDE [m] |",
        "|---|---|---|---|---|---|",
    ]
    for subset in SUBSETS:
      r, m = results["cvmdx_best_of_k"][subset], results.get("cvmdx_mean", {}).get(subset, {})
      lines.append(
          f"| {subset} | {r['num_scenarios']} | {fmt(m.get('energy_score'))} | "
          f"{fmt(r.get('nll_final'))} | {fmt(r.get('ece'), '{:.3f}')} | "
          f"{fmt(r.get('brier_min_fde'))} |"
      )
  return "\n".join(lines) + "\n"
