"""Evaluation: baselines, scores per method and class, figures, and the report run.

  baselines  constant velocity, constant acceleration + yaw rate, token-mean controls
  learned_baseline  the multiple-choice MLP's tokeniser check and report rows
  probabilistic  energy score, hypothesis-mixture NLL at 5 s, calibration (ECE) of p(c)
  scoring    per-scenario errors per method -> {method: {subset: {metric}}}, tables, KL per token
  figures    paper Fig. 1 (predictions), Fig. 3 (KL vs codebook usage), reliability diagram PNGs
  report     `run`: one evaluation of trained runs -> metrics.json, results.md, figures

The point metrics themselves (`ade`, `fde`, ...) are in `evaluation.metrics`.
"""
