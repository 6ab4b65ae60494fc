"""metrics.json names what it scored: each run's directory, checkpoint step and parameter id
(cvmdx_jax.evaluation.report_models.restored), on the session's tiny runs."""

import json
import re
import shutil

import jax
import numpy as np
import pytest

from cvmdx_jax.config.runs import DiffusionRunConfig
from cvmdx_jax.evaluation import report, report_models
from cvmdx_jax.models import unet1d
from cvmdx_jax.runs import layout, loaders, tokens
from cvmdx_jax.storage import checkpointing

pytestmark = pytest.mark.filterwarnings(  # the tiny runs put a few scenarios out of range
    "ignore::cvmdx_jax.inference.predictor.OutOfDistributionWarning"
)


def _add_a_later_step(run_dir, step: int) -> None:
  """Saves checkpoint `step` of a diffusion run: its EMA parameters (all the loader reads)
  scaled by 1.01, with the run's fingerprint (a training epoch, without the training)."""
  config = loaders.read_run_config(run_dir, DiffusionRunConfig, "diffusion")
  abstract = {"ema_params": unet1d.abstract_params(config.model)}
  tree, fingerprint = loaders.restore_latest(run_dir, abstract)
  later = {"ema_params": jax.tree.map(lambda x: x * 1.01, tree["ema_params"])}
  with checkpointing.Checkpoints(run_dir / layout.CHECKPOINTS) as ckpts:
    ckpts.save(step, later, {"fingerprint": fingerprint})


@pytest.fixture
def two_steps(tiny_runs, tmp_path):
  """A copy of the tiny diffusion run with checkpoints 1 and 2."""
  diffusion_dir = tmp_path / "diffusion"
  shutil.copytree(tiny_runs / "diffusion", diffusion_dir)
  _add_a_later_step(diffusion_dir, 2)
  assert sorted(int(p.name) for p in (diffusion_dir / "checkpoints").iterdir()) == [1, 2]
  return diffusion_dir


def test_the_loaded_checkpoints_are_named_and_an_older_one_shows(tiny_runs, two_steps):
  tokenizer_dir = tiny_runs / "tokenizer"
  latest = report_models.load(tokenizer_dir=tokenizer_dir, diffusion_dir=two_steps)
  tok, den = latest.checkpoints["tokenizer"], latest.checkpoints["diffusion"]
  assert set(latest.checkpoints) == {"tokenizer", "diffusion"}
  assert den["dir"] == str(two_steps) and den["checkpoint"] == 2
  assert re.fullmatch("[0-9a-f]{64}", den["params_id"])
  assert tok["dir"] == str(tokenizer_dir)
  assert tok["checkpoint"] == max(int(p.name) for p in (tokenizer_dir / "checkpoints").iterdir())
  # the id the tokeniser's training wrote beside its Gaussians for the same parameters
  _, gmeta = tokens.load_gaussians(tokens.gaussians_path(tokenizer_dir))
  assert tok["params_id"] == gmeta["checkpoint"]["params_id"]

  shutil.rmtree(two_steps / "checkpoints" / "2")  # the latest step is lost
  older = report_models.load(tokenizer_dir=tokenizer_dir, diffusion_dir=two_steps)
  assert older.checkpoints["diffusion"]["checkpoint"] == 1
  assert older.checkpoints["diffusion"]["params_id"] != den["params_id"]
  assert older.checkpoints["tokenizer"] == tok


@pytest.mark.slow  # an evaluation: ~30 s on the shared 2-core machine
def test_metrics_json_records_them(tiny_runs, two_steps, tmp_path):
  report.run(
      tokenizer_dir=tiny_runs / "tokenizer",
      diffusion_dir=two_steps,
      data_dir=tiny_runs / "data",
      workdir=tmp_path / "eval",
      max_scenarios=6,
      ddpm_scenarios=0,
      figures_per_class=0,
  )
  meta = json.loads((tmp_path / "eval" / "metrics.json").read_text())["_meta"]
  loaded = report_models.load(tokenizer_dir=tiny_runs / "tokenizer", diffusion_dir=two_steps)
  assert meta["checkpoints"] == loaded.checkpoints
  assert meta["checkpoints"]["diffusion"]["checkpoint"] == 2


def test_the_train_tokens_are_read_once(tiny_runs, monkeypatch):
  """`Predictor.load` reads tokens/train.npz and keeps it; the report's token usage is
  counted from what it kept, not from a second read."""
  calls, load = [], tokens.load_tokens
  monkeypatch.setattr(tokens, "load_tokens", lambda path: calls.append(path) or load(path))
  models = report_models.load(
      tokenizer_dir=tiny_runs / "tokenizer", diffusion_dir=tiny_runs / "diffusion"
  )
  assert calls == [tokens.tokens_path(tiny_runs / "tokenizer", "train")]
  train, _ = load(calls[0])
  assert models.usage.tolist() == np.bincount(train.q, minlength=len(models.usage)).tolist()
  assert models.usage.sum() == len(train.q)
