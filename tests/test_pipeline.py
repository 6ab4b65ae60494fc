"""Smoke test of the whole pipeline on tiny configs: SUMO data -> tokeniser ->
diffusion -> predictor -> evaluation report; plus the predictor's guarantees."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from configs import dataset as dataset_config
from configs import diffusion as diffusion_config
from configs import tokenizer as tokenizer_config
from cvmdx_jax import ego_motion, evaluation, report
from cvmdx_jax.data import dataset
from cvmdx_jax.predict import IncompatibleRunsError, Predictor
from cvmdx_jax.train import diffusion, tokenizer

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
  root = tmp_path_factory.mktemp("pipeline")
  data_dir = root / "data"
  dataset.build(dataset_config.get_config("tiny"), data_dir)
  tok = tokenizer_config.get_config("tiny")
  tok.data_dir = str(data_dir)
  tokenizer.train_and_evaluate(tok, root / "tokenizer")
  diff = diffusion_config.get_config("tiny")
  diff.data_dir, diff.tokenizer_dir = str(data_dir), str(root / "tokenizer")
  diffusion.train_and_evaluate(diff, root / "diffusion")
  return root


def test_report_has_every_method_subset_and_figure(runs):
  results = report.run(tokenizer_dir=runs / "tokenizer", diffusion_dir=runs / "diffusion",
                       data_dir=runs / "data", workdir=runs / "eval", max_scenarios=30,
                       ddpm_scenarios=3)
  saved = json.loads((runs / "eval" / "metrics.json").read_text())
  assert set(evaluation.METHODS) <= set(saved)
  for method in evaluation.METHODS:
    assert set(saved[method]) == set(evaluation.SUBSETS)
    for subset in evaluation.SUBSETS:
      row = saved[method][subset]
      assert {"ade", "fde", "miss_rate", "hit_rate", "num_scenarios"} <= set(row)
      assert row["ade"] <= row["fde"] + 1e-9 or method == "cvmdx_best_of_k"
  assert saved["cv"]["all"]["num_scenarios"] == 30
  assert saved["ddpm_single"]["all"]["num_scenarios"] == 3
  assert results["cvmdx_best_of_k"]["all"]["ade"] <= results["cvmdx_most_likely"]["all"]["ade"]
  for name in ("kl_vs_usage", "predictions_kl", "predictions_lcr", "predictions_lcl"):
    assert (runs / "eval" / f"{name}.png").stat().st_size > 1000
  assert "| Constant velocity |" in (runs / "eval" / "results.md").read_text()


def test_predictor_is_deterministic_and_chunk_independent(runs):
  scenarios = dataset.load_split(runs / "data", "test").take(np.arange(6))
  predictor = Predictor.load(runs / "tokenizer", runs / "diffusion")
  a = predictor(scenarios, seed=3)
  b = Predictor.load(runs / "tokenizer", runs / "diffusion", chunk_size=4)(scenarios, seed=3)
  c = predictor(scenarios, seed=4)
  np.testing.assert_allclose(a.prediction.trajectories, b.prediction.trajectories, atol=1e-4)
  np.testing.assert_array_equal(a.q, b.q)
  assert not np.allclose(a.prediction.trajectories, c.prediction.trajectories)
  assert a.prediction.trajectories.shape == (6, 9, 125, 2)
  np.testing.assert_allclose(a.hypotheses.probs.sum(-1), 1.0, atol=1e-6)


def test_predictor_refuses_bad_scenarios(runs):
  scenarios = dataset.load_split(runs / "data", "test").take(np.arange(2))
  predictor = Predictor.load(runs / "tokenizer", runs / "diffusion")
  xi = scenarios.xi.copy()
  xi[1, 0, 3, 0] = np.nan
  with pytest.raises(ValueError, match="'xi' holds NaN/inf \\(scenario 1\\)"):
    predictor(scenarios.__class__(**{**scenarios.as_dict(), "xi": xi}))
  with pytest.raises(ValueError, match="'xi' has shape"):
    predictor(scenarios.__class__(**{**scenarios.as_dict(), "xi": scenarios.xi[:, :, :50]}))


def test_runs_that_do_not_belong_together_are_refused(runs, tmp_path):
  other = tokenizer_config.get_config("tiny,q=5")
  other.data_dir = str(runs / "data")
  tokenizer.train_and_evaluate(other, tmp_path / "other_tokenizer")
  with pytest.raises(IncompatibleRunsError, match="5"):
    Predictor.load(tmp_path / "other_tokenizer", runs / "diffusion")


def test_ego_conditioned_run_trains_loads_and_predicts(runs, tmp_path):
  diff = diffusion_config.get_config("tiny")
  diff.data_dir, diff.tokenizer_dir = str(runs / "data"), str(runs / "tokenizer")
  diff.diffusion.conditioning = "ego_film_residual"
  data, *_ = diffusion.training_data(diff)
  train = dataset.load_split(runs / "data", "train")
  ego = np.asarray(ego_motion.ego_features(train.xi, train.mask))
  base = np.asarray(ego_motion.residual_controls(ego, diff.diffusion.residual_decay_s))
  scale = np.asarray(diff.diffusion.control_scale)
  np.testing.assert_allclose(data["ego"], ego)
  np.testing.assert_allclose(data["x0"], np.clip((train.controls - base) / scale, -1, 1),
                             atol=1e-6)
  diffusion.train_and_evaluate(diff, tmp_path / "ego")
  predictor = Predictor.load(runs / "tokenizer", tmp_path / "ego")
  assert predictor.sampling.conditioning == "ego_film_residual"
  assert predictor.denoiser.unet.cond_dim == ego_motion.NUM_FEATURES
  scenarios = dataset.load_split(runs / "data", "test").take(np.arange(5))
  a = predictor(scenarios, seed=1)
  b = Predictor.load(runs / "tokenizer", tmp_path / "ego", chunk_size=2)(scenarios, seed=1)
  np.testing.assert_allclose(a.prediction.trajectories, b.prediction.trajectories, atol=1e-4)
  assert a.prediction.trajectories.shape == (5, 9, 125, 2)
  with pytest.raises(ValueError, match="diffusion.conditioning"):
    diff.diffusion.conditioning = "ego"
    diffusion.train_and_evaluate(diff, tmp_path / "bad")
  assert not (tmp_path / "bad").exists()


def test_unknown_split_raises_and_writes_nothing(runs, tmp_path):
  out = tmp_path / "eval"
  with pytest.raises(ValueError, match="validation"):
    report.run(tokenizer_dir=runs / "tokenizer", diffusion_dir=runs / "diffusion",
               data_dir=runs / "data", workdir=out, split="validation")
  assert not out.exists()


def test_codebook_ablation_script(runs, tmp_path):
  out = tmp_path / "ablation"
  proc = subprocess.run(
      [sys.executable, str(REPO / "experiments" / "ablate_codebook.py"),
       f"--data_dir={runs / 'data'}", f"--workdir={out}", "--codebook_sizes=4,6",
       "--tokenizer_preset=tiny", "--diffusion_preset=tiny", "--max_scenarios=12"],
      env=dict(os.environ, PYTHONPATH=str(REPO)), capture_output=True, text=True, timeout=600)
  assert proc.returncode == 0, proc.stderr[-3000:]
  rows = [line for line in (out / "ablation.md").read_text().splitlines()
          if line.startswith("| cvq |")]
  assert [r.split("|")[2].strip() for r in rows] == ["4", "6"]
  saved = json.loads((out / "ablation.json").read_text())
  assert saved["cvq_q6"]["cvmdx_mean"]["all"]["num_scenarios"] == 12


def test_codebook_health_script(runs, tmp_path):
  out = tmp_path / "health"
  proc = subprocess.run(
      [sys.executable, str(REPO / "experiments" / "codebook_health.py"),
       "--config=configs/tokenizer.py:tiny", f"--config.data_dir={runs / 'data'}",
       f"--workdir={out}", "--codebook_sizes=4"],
      cwd=REPO, env=dict(os.environ, PYTHONPATH=str(REPO)), capture_output=True, text=True,
      timeout=600)
  assert proc.returncode == 0, proc.stderr[-3000:]
  lines = (out / "codebook_health.md").read_text().splitlines()
  cells = {line.split("|")[2].strip(): line.split("|")[1:-1] for line in lines[2:]}
  assert set(cells) == {"constant velocity", "cvq", "vq"}
  test = dataset.load_split(runs / "data", "test")
  cv = test.xi[:, 0, -1, None, 2:4] * (0.04 * np.arange(1, 126))[None, :, None]
  err = np.linalg.norm(cv - test.future, axis=-1)
  np.testing.assert_allclose([float(v) for v in cells["constant velocity"][-2:]],
                             [err.mean(), err[:, -1].mean()], atol=1e-3)
  for kind in ("cvq", "vq"):
    assert all(np.isfinite(float(v)) for v in cells[kind][-2:])
