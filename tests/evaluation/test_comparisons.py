"""A report's paired comparisons: which rows exist and their differences by hand."""

import numpy as np

from cvmdx_jax.evaluation import comparisons


def test_planned_rows_need_both_methods():
  rows = comparisons.planned({"cvmdx_mean": {}, "cv": {}})
  assert ("cvmdx_mean", "cv", "energy_score", "all") in rows
  assert ("cvmdx_mean", "cv", "ade", "lcl") in rows
  assert not any(r[1] == "mlp_mean" for r in rows)


def test_paired_difference_by_hand():
  errors = {
      "cvmdx_mean": {"ade": np.array([1.0, 2.0, 3.0, 4.0])},
      "cv": {"ade": np.array([2.0, 3.0, 4.0, 5.0])},
  }
  rows = comparisons.paired(errors, [1, 1, 1, 1], [1, 2, 3, 4], [0, 0, 1, 2])
  by = {(r["metric"], r["subset"]): r["by_seed"][""] for r in rows}
  assert by[("ade", "all")]["difference"] == -1.0
  assert by[("ade", "all")]["verdict"] == "better"  # every vehicle's difference is -1
  assert by[("ade", "lcr")]["a"] == 3.0
  assert "| cvmdx_mean - cv | ade | all | -1.000 [-1.000, -1.000] better |" in (
      comparisons.markdown(rows)
  )
