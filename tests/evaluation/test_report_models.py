"""metrics.json names what it scored: each run's directory, checkpoint step and parameter id
(cvmdx_jax.evaluation.report_models.restored), on the session's tiny runs."""

import json
import re
import shutil

import pytest

from cvmdx_jax.evaluation import report, report_models
from cvmdx_jax.runs import tokens
from tests import fixtures_runs

pytestmark = pytest.mark.filterwarnings(  # the tiny runs put a few scenarios out of range
    "ignore::cvmdx_jax.inference.predictor.OutOfDistributionWarning"
)


def test_metrics_record_the_checkpoints_and_an_older_one_shows(tiny_runs, tmp_path):
  diffusion_dir = tmp_path / "diffusion"
  config = fixtures_runs.diffusion_config_for(tiny_runs / "data", tiny_runs / "tokenizer")
  config.train.num_epochs = 2  # checkpoints 1 and 2: an older step to fall back to
  fixtures_runs.train_diffusion(config, diffusion_dir)
  steps = sorted(int(p.name) for p in (diffusion_dir / "checkpoints").iterdir())
  assert steps == [1, 2]
  report.run(
      tokenizer_dir=tiny_runs / "tokenizer",
      diffusion_dir=diffusion_dir,
      data_dir=tiny_runs / "data",
      workdir=tmp_path / "eval",
      max_scenarios=6,
      ddpm_scenarios=0,
      figures_per_class=0,
  )
  meta = json.loads((tmp_path / "eval" / "metrics.json").read_text())["_meta"]
  tok, den = meta["checkpoints"]["tokenizer"], meta["checkpoints"]["diffusion"]
  assert set(meta["checkpoints"]) == {"tokenizer", "diffusion"}
  assert den["dir"] == str(diffusion_dir) and den["checkpoint"] == steps[-1]
  assert tok["dir"] == str(tiny_runs / "tokenizer")
  assert tok["checkpoint"] == max(
      int(p.name) for p in (tiny_runs / "tokenizer" / "checkpoints").iterdir()
  )
  # the id the tokeniser's training wrote beside its Gaussians for the same parameters
  _, gmeta = tokens.load_gaussians(tokens.gaussians_path(tiny_runs / "tokenizer"))
  assert tok["params_id"] == gmeta["checkpoint"]["params_id"]
  assert re.fullmatch("[0-9a-f]{64}", den["params_id"])

  shutil.rmtree(diffusion_dir / "checkpoints" / str(steps[-1]))  # the latest step is lost
  older = report_models.load(tokenizer_dir=tiny_runs / "tokenizer", diffusion_dir=diffusion_dir)
  assert older.checkpoints["diffusion"]["checkpoint"] == steps[-2]
  assert older.checkpoints["diffusion"]["params_id"] != den["params_id"]
  assert older.checkpoints["tokenizer"] == tok
