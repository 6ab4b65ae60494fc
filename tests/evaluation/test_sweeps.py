"""cvmdx_jax.evaluation.sweeps: the hypothesis sweep's method specs and the choice rule, by hand."""

import pytest

from cvmdx_jax.config.sampling import HypothesisConfig
from cvmdx_jax.evaluation import sweeps


def test_method_specs_keep_the_run_settings():
  base = HypothesisConfig(c_max=4, reg_covar=1e-3)
  assert sweeps.hypothesis_config("bic", base) == base
  k = sweeps.hypothesis_config("kmeans:0.5", base)
  assert (k.method, k.endpoint_weight, k.c_max, k.reg_covar) == ("kmeans", 0.5, 4, 1e-3)
  for bad in ("gmm", "bic:1"):
    with pytest.raises(ValueError, match="is not 'bic' or"):
      sweeps.hypothesis_config(bad, base)


def test_choice_is_the_lowest_brier_within_the_mean_ade_tolerance():
  ref = {"method": "bic", "num_samples": 9, "mean_ade": 1.00, "brier_min_fde": 2.0}
  rows = [
      ref,
      {"method": "kmeans:0", "num_samples": 9, "mean_ade": 1.00, "brier_min_fde": 1.8},
      {"method": "kmeans:0", "num_samples": 36, "mean_ade": 1.015, "brier_min_fde": 1.7},
      {"method": "kmeans:0", "num_samples": 64, "mean_ade": 1.03, "brier_min_fde": 1.6},
  ]
  assert sweeps.choose_hypotheses(rows, ref, 0.02) is rows[2]  # 64 is 3 % worse
  assert sweeps.choose_hypotheses(rows, ref, 0.05) is rows[3]
  assert sweeps.choose_hypotheses(rows, ref, 0.05, max_num_samples=36) is rows[2]
