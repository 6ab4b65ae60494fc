"""experiments/calibrate_probs.py on the session's tiny runs: one row per temperature of the
grid, the chosen one the lowest log loss, and the runs' predictions at it."""

import json

import numpy as np
import pytest

from cvmdx_jax.data import dataset
from cvmdx_jax.evaluation import prob_calibration, report_models
from tests.subprocess_env import run_script

pytestmark = pytest.mark.filterwarnings(  # the tiny runs put a few scenarios out of range
    "ignore::cvmdx_jax.inference.predictor.OutOfDistributionWarning"
)


def test_the_table_and_the_chosen_temperature(tiny_runs, tmp_path):
  out = tmp_path / "calibration.json"
  proc = run_script(
      "calibrate_probs",
      f"--tokenizer_dir={tiny_runs / 'tokenizer'}",
      f"--diffusion_dir={tiny_runs / 'diffusion'}",
      f"--data_dir={tiny_runs / 'data'}",
      "--split=val",
      f"--out={out}",
  )
  assert proc.returncode == 0, proc.stderr
  table = json.loads(out.read_text())
  rows = table["rows"]
  assert [r["temperature"] for r in rows] == list(prob_calibration.TEMPERATURES)
  losses = [r["log_loss"] for r in rows]
  assert table["chosen"] == prob_calibration.choose(losses)
  assert f"chosen: prob_temperature={table['chosen']:g}" in proc.stdout
  assert all(np.isfinite(losses)) and all(0 <= r["ece"] <= 1 for r in rows)

  # the loss at temperature 1 is that of the run's own p(c) on the same scenarios
  models = report_models.load(
      tokenizer_dir=tiny_runs / "tokenizer",
      diffusion_dir=tiny_runs / "diffusion",
      sampling_overrides={"prob_temperature": 1.0},
  )
  scenarios = dataset.load_balanced(tiny_runs / "data", "val", 0, 0)
  hyp = models.predictor(scenarios, seed=0).hypotheses
  closest = prob_calibration.closest_hypothesis(hyp.means, hyp.probs, scenarios.future)
  p = np.asarray(hyp.probs)[np.arange(len(closest)), closest]
  np.testing.assert_allclose(losses[-1], np.mean(-np.log(np.maximum(p, 1e-6))), rtol=1e-5)


def test_the_report_predicts_with_an_overridden_temperature(tiny_runs):
  models = report_models.load(
      tokenizer_dir=tiny_runs / "tokenizer",
      diffusion_dir=tiny_runs / "diffusion",
      sampling_overrides={"prob_temperature": 0.5, "num_samples": 6},
  )
  sampling = models.predictor.sampling
  assert sampling.hypotheses.prob_temperature == 0.5 and sampling.num_samples == 6
