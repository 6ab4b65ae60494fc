"""Evaluation scoring against hand-worked values: the added metrics (final lon / lat,
Brier-minFDE, target lane, delta rank correlation, out-of-distribution share), their
summary per subset and the refusal of non-finite predictions."""

import numpy as np
import pytest

from cvmdx_jax.data.scenarios import Scenarios
from cvmdx_jax.evaluation import learned_baseline, mdn_rows, score_tables, scoring
from cvmdx_jax.inference.sampling import Prediction
from cvmdx_jax.multimodal.hypotheses import Hypotheses


def _line(dx, dy, t=125):
  """A trajectory moving linearly from (0, 0) to (dx, dy) at 5 s: (t, 2)."""
  return np.linspace(0, 1, t)[:, None] * np.array([dx, dy], np.float32)


def _hypothesis_fixture():
  """Three scenarios (kl, lcr, lcl), ground truth ending at (100, 0), (100, -3.5),
  (100, 3.5), two used hypothesis slots and one unused."""
  gt = np.stack([_line(100, 0), _line(100, -3.5), _line(100, 3.5)])
  hyps = np.stack(
      [
          np.stack([_line(97, 4), _line(101, 0), _line(100, 0)]),  # kl: slot 1 closest (1 m)
          np.stack([_line(102, 0), _line(100, -2.5), _line(0, 0)]),  # lcr: slot 1 (1 m)
          np.stack([_line(104, 3.5), _line(100, -1), _line(0, 0)]),  # lcl: slot 0 (4 m)
      ]
  ).astype(np.float32)
  probs = np.array([[0.7, 0.3, 0.0], [0.9, 0.1, 0.0], [0.15, 0.85, 0.0]], np.float32)
  return hyps, probs, gt, np.array([0, 1, 2])


def test_single_trajectory_final_lon_lat_by_hand():
  gt = np.stack([_line(100, 0), _line(80, 3.5)])
  pred = np.stack([_line(97, 4), _line(81, 3.0)])
  errors = scoring.single_trajectory_errors(pred, gt)
  np.testing.assert_allclose(errors["final_lon"], [3.0, 1.0], atol=1e-5)
  np.testing.assert_allclose(errors["final_lat"], [4.0, 0.5], atol=1e-5)
  np.testing.assert_allclose(errors["fde"], [5.0, np.hypot(1.0, 0.5)], atol=1e-5)


def test_best_of_k_errors_by_hand():
  hyps, probs, gt, labels = _hypothesis_fixture()
  errors = scoring.best_of_k_errors(hyps, probs, gt, labels)
  # the unused slot 2 of scenario 0 is a perfect match but must not count
  np.testing.assert_allclose(errors["fde"], [1.0, 1.0, 4.0], atol=1e-5)
  np.testing.assert_allclose(errors["final_lon"], [1.0, 0.0, 4.0], atol=1e-5)
  np.testing.assert_allclose(errors["final_lat"], [0.0, 1.0, 0.0], atol=1e-5)
  # minFDE + (1 - p)^2 of the closest hypothesis
  np.testing.assert_allclose(
      errors["brier_min_fde"], [1.0 + 0.7**2, 1.0 + 0.9**2, 4.0 + 0.85**2], atol=1e-5
  )
  # lcr: slot 1 ends 1 m from the target lane centre but has p = 0.1 < 0.2, slot 0 ends
  # 3.5 m away -> miss; lcl: slot 0 (p = 0.15 < 0.2) is in the lane, slot 1 is not -> miss
  lane = errors["target_lane_hit"]
  assert lane.mask.tolist() == [True, False, False]
  np.testing.assert_allclose(lane.data[1:], [0.0, 0.0])
  probs_lcl = probs.copy()
  probs_lcl[2] = [0.2, 0.8, 0.0]
  lane = scoring.best_of_k_errors(hyps, probs_lcl, gt, labels)["target_lane_hit"]
  np.testing.assert_allclose(lane.data[1:], [0.0, 1.0])


def test_summarise_averages_per_subset_and_leaves_target_lane_out_of_kl():
  hyps, probs, gt, labels = _hypothesis_fixture()
  probs[2] = [0.2, 0.8, 0.0]
  labels = np.array([0, 1, 2])
  hyps, probs, gt, labels = (np.concatenate([a, a]) for a in (hyps, probs, gt, labels))
  errors = {"cvmdx_best_of_k": scoring.best_of_k_errors(hyps, probs, gt, labels)}
  out = scoring.summarise(errors, labels)["cvmdx_best_of_k"]
  assert "target_lane_hit" not in out["kl"]
  assert out["all"]["target_lane_hit"] == pytest.approx(0.5)  # lcr miss, lcl hit
  assert out["lcl"]["target_lane_hit"] == pytest.approx(1.0)
  assert out["lcr"]["target_lane_hit"] == pytest.approx(0.0)
  assert out["all"]["brier_min_fde"] == pytest.approx((1.49 + 1.81 + 4.64) / 3, abs=1e-5)
  assert out["kl"]["final_lon"] == pytest.approx(1.0, abs=1e-5)
  assert out["all"]["num_scenarios"] == 6 and out["lcr"]["num_scenarios"] == 2


def test_summarise_refuses_non_finite_values():
  errors = {"cv": {"ade": np.array([1.0, np.nan, 2.0]), "fde": np.ones(3)}}
  with pytest.raises(scoring.NonFinitePredictionError, match=r"cv ade .*\[1\]"):
    scoring.summarise(errors, np.array([0, 1, 2]))
  masked = np.ma.masked_array([np.nan, 1.0, 0.0], mask=[True, False, False])
  out = scoring.summarise({"m": {"target_lane_hit": masked}}, np.array([0, 1, 2]))
  assert out["m"]["all"]["target_lane_hit"] == pytest.approx(0.5)  # a masked NaN is no value


def test_delta_rank_correlation_by_hand():
  # all: ranks of ade (1, 2, 4, 3, 5, 6) against (1, ..., 6): sum d^2 = 2,
  # rho = 1 - 6 * 2 / (6 * 35) = 0.942857...
  delta = np.array([1.0, 2.0, 3.0, 4.0, 5.0, 6.0])
  ade = np.array([0.1, 0.2, 0.4, 0.3, 0.5, 0.6])
  labels = np.array([0, 0, 0, 1, 1, 2])
  out = scoring.delta_rank_correlation(delta, ade, labels)
  assert out["all"]["delta_ade_spearman"] == pytest.approx(1 - 12 / 210)
  assert out["kl"]["delta_ade_spearman"] == pytest.approx(1.0)
  assert 0 <= out["all"]["delta_ade_spearman_p"] < 0.05
  assert np.isnan(out["lcr"]["delta_ade_spearman"])  # 2 scenarios: undefined
  assert np.isnan(out["lcl"]["delta_ade_spearman_p"])
  reverse = scoring.delta_rank_correlation(delta[:3], ade[:3][::-1], labels[:3])
  assert reverse["kl"]["delta_ade_spearman"] == pytest.approx(-1.0)


def _scenarios(m):
  t = np.zeros(m, np.int64)
  return Scenarios(
      xi=np.zeros((m, 9, 75, 4), np.float32),
      mask=np.ones((m, 9, 75), bool),
      future=np.zeros((m, 125, 2), np.float32),
      controls=np.zeros((m, 125, 2), np.float32),
      v0=np.ones(m, np.float32),
      psi0=np.zeros(m, np.float32),
      label=t,
      time_to_lane_change=t - 1,
      recording_id=t + 7,
      track_id=np.arange(m) + 100,
      frame=t + 250,
  )


def _prediction(m, k=3, n=4):
  hyp = Hypotheses(
      num_modes=np.ones(m, np.int32),
      num_components=np.ones(m, np.int32),
      labels=np.zeros((m, n), np.int32),
      means=np.zeros((m, k, 125, 2)),
      probs=np.tile([1.0, 0.0, 0.0], (m, 1)),
      bic=np.full((m, k), np.inf),
  )  # an infinite BIC is legitimate
  return Prediction(
      controls=np.zeros((m, n, 125, 2)),
      trajectories=np.zeros((m, n, 125, 2)),
      mean=np.zeros((m, 125, 2)),
      hypotheses=hyp,
  )


def test_check_finite_names_the_scenarios():
  scenarios = _scenarios(4)
  scoring.check_finite(_prediction(4), scenarios, "cVMDx")  # finite: passes
  pred = _prediction(4)
  pred.trajectories[1, 2, 50, 0] = np.nan
  pred.hypotheses.means[3, 0, 10, 1] = np.inf
  with pytest.raises(
      scoring.NonFinitePredictionError,
      match=r"cVMDx: non-finite predictions for 2 of 4 scenarios: "
      r"#1 \(recording 7, track 101, frame 250\), #3 \(recording 7, "
      r"track 103",
  ):
    scoring.check_finite(pred, scenarios, "cVMDx")
  assert issubclass(scoring.NonFinitePredictionError, ValueError)


def test_markdown_tables_show_the_added_metrics():
  hyps, probs, gt, labels = _hypothesis_fixture()
  errors = {
      "cvmdx_best_of_k": scoring.best_of_k_errors(hyps, probs, gt, labels),
      "cvmdx_mean": {
          **scoring.single_trajectory_errors(gt + 1.0, gt),
          "out_of_distribution": np.array([0.0, 1.0, 0.0]),
      },
  }
  results = scoring.summarise(errors, labels)
  text = score_tables.markdown_tables(results)
  assert "Brier-minFDE [m]" in text and "final lon [m]" in text and "target lane" in text
  mean_row = next(line for line in text.splitlines() if line.startswith("| cVMDx mean"))
  assert mean_row.split("|")[4].strip() == "1.00"  # final lon of a 1 m shift
  ood_row = next(line for line in text.splitlines() if line.startswith("| all |"))
  assert ood_row.split("|")[3].strip() == "33.3%"


def test_learned_baseline_rows_by_hand():
  """Most likely = the argmax-p head, mean = the p-weighted mean of the heads, best of K
  over every head (also one whose probability underflowed to 0)."""
  hyps, _, gt, labels = _hypothesis_fixture()
  hyps[:, 2] = hyps[:, 0]  # three real heads per scenario
  hyps[1, 2] = gt[1]  # lcr: a perfect head with p = 0
  probs = np.array([[0.5, 0.5, 0.0], [0.9, 0.1, 0.0], [0.25, 0.25, 0.5]], np.float32)
  errors = learned_baseline.errors(hyps, probs, gt, labels)
  # kl: 0.5 (97, 4) + 0.5 (101, 0) = (99, 2); lcr: 0.9 (102, 0) + 0.1 (100, -2.5) =
  # (101.8, -0.25); lcl: 0.75 (104, 3.5) + 0.25 (100, -1) = (103, 2.375)
  np.testing.assert_allclose(
      errors["mlp_mean"]["fde"],
      [np.hypot(1, 2), np.hypot(1.8, 3.25), np.hypot(3, 1.125)],
      atol=1e-4,
  )
  # kl: a tie goes to the first head, (97, 4)
  np.testing.assert_allclose(
      errors["mlp_most_likely"]["fde"], [5.0, np.hypot(2, 3.5), 4.0], atol=1e-4
  )
  np.testing.assert_allclose(errors["mlp_best_of_k"]["fde"], [1.0, 0.0, 4.0], atol=1e-5)
  # lcl: heads 0 and 2 tie at 4 m, the first (p = 0.25) is taken
  np.testing.assert_allclose(
      errors["mlp_best_of_k"]["brier_min_fde"], [1.0 + 0.5**2, 0.0 + 1.0, 4.0 + 0.75**2], atol=1e-5
  )


def test_calibration_by_hand():
  hyps, probs, gt, labels = _hypothesis_fixture()
  ece, diagram = scoring.calibration(hyps, probs, gt, labels)
  # closest: slot 1 (p 0.3), slot 1 (p 0.1), slot 0 (p 0.15); the other used slots
  # (p 0.7, 0.9, 0.85) are not; bin 1 holds 0.1 and 0.15, both closest
  np.testing.assert_allclose(ece["all"]["ece"], (0.7 + 0.7 + 0.9 + 1.75 + 0.85) / 6, rtol=1e-5)
  np.testing.assert_allclose(ece["kl"]["ece"], 0.7, rtol=1e-5)
  assert diagram["count"] == [0, 2, 0, 1, 0, 0, 0, 1, 1, 1]
  np.testing.assert_allclose(diagram["confidence"][1], 0.125, rtol=1e-5)
  assert diagram["accuracy"][1] == 1.0 and diagram["accuracy"][7] == 0.0
  assert np.isnan(diagram["accuracy"][0])


def test_markdown_tables_show_the_probabilistic_scores():
  hyps, probs, gt, labels = _hypothesis_fixture()
  errors = {
      "cvmdx_best_of_k": {
          **scoring.best_of_k_errors(hyps, probs, gt, labels),
          "nll_final": np.array([1.0, 2.0, 3.0]),
      },
      "cvmdx_mean": {
          **scoring.single_trajectory_errors(gt + 1.0, gt),
          "energy_score": np.array([0.5, 0.5, 0.5]),
      },
  }
  results = scoring.summarise(errors, labels)
  for subset, row in scoring.calibration(hyps, probs, gt, labels)[0].items():
    results["cvmdx_best_of_k"][subset].update(row)
  text = score_tables.markdown_tables(results)
  row = next(line for line in text.splitlines() if line.startswith("| kl | 1 | 0.50"))
  assert [c.strip() for c in row.split("|")[4:7]] == ["1.00", "0.700", "1.49"]


def test_every_row_a_report_can_hold_has_a_title():
  rows = scoring.METHODS + learned_baseline.METHODS + mdn_rows.METHODS
  assert set(rows) <= set(score_tables.METHOD_TITLES)
  assert len(set(score_tables.METHOD_TITLES.values())) == len(score_tables.METHOD_TITLES)
