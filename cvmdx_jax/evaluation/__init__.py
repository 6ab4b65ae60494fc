"""Evaluation: baselines, scores per method and class, figures, and the report run.

  baselines  constant velocity, constant acceleration + yaw rate, token-mean controls
  learned_baseline  the multiple-choice MLP's tokeniser check and report rows
  mdn_rows   the mixture density network's report rows
  probabilistic  (weighted) energy score, hypothesis-mixture NLL at 5 s, calibration of p(c)
  scoring    per-scenario errors per method -> {method: {subset: {metric}}}
  score_tables  the report's markdown tables of those
  token_kl   KL per codebook entry between data and model 5 s positions (paper Fig. 3)
  comparisons  paired differences of a report with vehicle-bootstrap intervals
  figures    paper Fig. 1 (predictions), Fig. 3 (KL vs codebook usage), reliability PNGs
  report     `run` = report_models.load + `evaluate` (-> report_files.Report) + write
  report_models, report_files  the runs of a report loaded once; its files written as one

The quality benchmark (experiments/benchmark_quality.py), the same definitions for every
model (each takes `inference.distributions.WeightedSamples` or `GaussianMixture`):
  regions    density at 1..5 s (kernels and a wide tail chosen on val, or a mixture's own),
             NLL, highest-density regions (coverage, area)
  model_scores  per-scenario proper and point scores of one model
  predictive    every model's prediction as a `model_scores.Model`
  intervals  paired differences with 95 % vehicle-bootstrap intervals
  conformal  split-conformal calibration of region levels (and per delta tercile), p(c) sets
  quality, quality_tables  one trained run scored on large test sets; its tables

The point metrics themselves (`ade`, `fde`, ...) are in `evaluation.metrics`.
"""
