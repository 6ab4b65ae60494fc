"""Smoke test of the whole pipeline on tiny configs: SUMO data -> tokeniser ->
diffusion -> predictor -> evaluation report; plus the predictor's guarantees."""

import contextlib
import dataclasses
import errno
import json
import os
import shutil
import subprocess
import sys
import types
from pathlib import Path

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
import pytest

from configs import baseline as baseline_config
from configs import dataset as dataset_config
from configs import diffusion as diffusion_config
from configs import distill as distill_config
from configs import tokenizer as tokenizer_config
from cvmdx_jax import ego_motion
from cvmdx_jax.config.runs import BaselineRunConfig, DiffusionRunConfig, DistillRunConfig
from cvmdx_jax.data import dataset
from cvmdx_jax.data.scenarios import balanced_indices
from cvmdx_jax.evaluation import learned_baseline, report, report_models, scoring
from cvmdx_jax.inference.bundles import load_baseline, load_denoiser
from cvmdx_jax.inference.predictor import IncompatibleRunsError, OutOfDistributionWarning, Predictor
from cvmdx_jax.models import unet1d
from cvmdx_jax.runs import fingerprints
from cvmdx_jax.storage import atomic, checkpointing, checksums, identity
from cvmdx_jax.train import baseline, diffusion, distill
from tests import fixtures_runs
from tests.subprocess_env import environ
from tests.train import toy

# The tiny runs put a few scenarios beyond the tokeniser's training range; the warning is
# tested in tests/inference, here it is expected.
pytestmark = pytest.mark.filterwarnings(
    "ignore::cvmdx_jax.inference.predictor.OutOfDistributionWarning"
)

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture
def runs(tiny_runs):
  """The session's tiny data, tokeniser and denoiser (tests/fixtures_runs.py); read-only."""
  return tiny_runs


def test_report_has_every_method_subset_and_figure(runs, tmp_path):
  results = report.run(
      tokenizer_dir=runs / "tokenizer",
      diffusion_dir=runs / "diffusion",
      data_dir=runs / "data",
      workdir=tmp_path / "eval",
      max_scenarios=30,
      ddpm_scenarios=3,
  )
  saved = json.loads((tmp_path / "eval" / "metrics.json").read_text())
  assert set(scoring.METHODS) <= set(saved)
  for method in scoring.METHODS:
    assert set(saved[method]) == set(scoring.SUBSETS)
    for subset in scoring.SUBSETS:
      row = saved[method][subset]
      assert {
          "ade",
          "fde",
          "final_lon",
          "final_lat",
          "miss_rate",
          "hit_rate",
          "num_scenarios",
      } <= set(row)
      assert np.isfinite(row["ade"]) and np.isfinite(row["fde"])
      assert min(row["ade"], row["fde"]) >= 0
      # per scenario max(|dx|, |dy|) <= fde <= |dx| + |dy|; averaged, hypot(mean |dx|,
      # mean |dy|) <= mean fde (Minkowski)
      assert max(row["final_lon"], row["final_lat"]) <= row["fde"] + 1e-5
      assert np.hypot(row["final_lon"], row["final_lat"]) <= row["fde"] + 1e-5
      assert row["fde"] <= row["final_lon"] + row["final_lat"] + 1e-5
  best = saved["cvmdx_best_of_k"]
  for subset in scoring.SUBSETS:
    assert best[subset]["fde"] <= best[subset]["brier_min_fde"] <= best[subset]["fde"] + 1
    assert ("target_lane_hit" in best[subset]) == (subset != "kl")
  assert 0 <= best["all"]["target_lane_hit"] <= 1
  for subset in scoring.SUBSETS:
    assert 0 <= best[subset]["ece"] <= 1 and np.isfinite(best[subset]["nll_final"])
    # >= 0 by the triangle inequality
    assert 0 <= saved["cvmdx_mean"][subset]["energy_score"] < np.inf
  diagram = saved["_meta"]["reliability"]
  assert sum(diagram["count"]) >= 30 and len(diagram["accuracy"]) == 10
  assert (tmp_path / "eval" / "reliability.png").stat().st_size > 1000
  mean = saved["cvmdx_mean"]
  assert 0 <= mean["all"]["out_of_distribution"] <= 1
  assert -1 <= mean["all"]["delta_ade_spearman"] <= 1
  assert saved["_meta"]["out_of_distribution"]["share"] == mean["all"]["out_of_distribution"]
  assert saved["cv"]["all"]["num_scenarios"] == 30
  assert saved["ddpm_single"]["all"]["num_scenarios"] == 3
  assert results["cvmdx_best_of_k"]["all"]["ade"] <= results["cvmdx_most_likely"]["all"]["ade"]
  for name in ("kl_vs_usage", "predictions_kl", "predictions_lcr", "predictions_lcl"):
    assert (tmp_path / "eval" / f"{name}.png").stat().st_size > 1000
  table = (tmp_path / "eval" / "results.md").read_text()
  assert "| Constant velocity |" in table and "Brier-minFDE" in table
  # predictions.npz: the evaluated scenarios row by row, their errors recomputed from the
  # stored mean and hypotheses against the split's own futures
  arrays = checksums.read_npz(tmp_path / "eval" / "predictions.npz")
  split = dataset.load_split(runs / "data", "test")
  rows = balanced_indices(split.label, 0, 30)
  for field in ("recording_id", "track_id", "frame", "label"):
    np.testing.assert_array_equal(arrays[field], getattr(split, field)[rows])
  future = split.future[rows]
  assert arrays["mean"].shape == (30, 125, 2) and arrays["hypotheses"].shape[:2] == (30, 3)
  np.testing.assert_allclose(arrays["probs"].sum(-1), 1.0, atol=1e-5)
  ade = np.linalg.norm(arrays["mean"] - future, axis=-1).mean(-1)
  np.testing.assert_allclose(arrays["cvmdx_mean_ade"], ade, rtol=1e-5)
  hyp_fde = np.linalg.norm(arrays["hypotheses"][:, :, -1] - future[:, None, -1], axis=-1)
  np.testing.assert_allclose(
      arrays["cvmdx_best_of_k_fde"],
      np.where(arrays["probs"] > 0, hyp_fde, np.inf).min(-1),
      rtol=1e-5,
  )
  for method in ("cvmdx_mean", "cvmdx_best_of_k", "cv", "ca"):
    for metric in ("ade", "fde"):
      assert np.isclose(arrays[f"{method}_{metric}"].mean(), saved[method]["all"][metric])
  assert "out of distribution" in table and "Spearman" in table
  assert "energy score of N [m]" in table and "ECE of p(c)" in table


def test_report_with_and_without_the_learned_baseline(runs, tmp_path, monkeypatch):
  config = baseline_config.get_config("tiny")
  config.data_dir, config.tokenizer_dir = str(runs / "data"), str(runs / "tokenizer")
  baseline.train(BaselineRunConfig.from_config(config), tmp_path / "baseline")
  kw = dict(
      tokenizer_dir=runs / "tokenizer",
      diffusion_dir=runs / "diffusion",
      data_dir=runs / "data",
      max_scenarios=12,
      ddpm_scenarios=0,
  )
  report.run(**kw, workdir=tmp_path / "with", baseline_dir=tmp_path / "baseline")
  report.run(**kw, workdir=tmp_path / "without")
  with_, without = (
      json.loads((tmp_path / d / "metrics.json").read_text()) for d in ("with", "without")
  )
  assert set(with_) - set(without) == set(learned_baseline.METHODS)
  for method in learned_baseline.METHODS:
    assert set(with_[method]) == set(scoring.SUBSETS)
    assert with_[method]["all"]["num_scenarios"] == 12
  for subset in scoring.SUBSETS:  # best of K <= each single read-out
    best = with_["mlp_best_of_k"][subset]
    assert best["ade"] <= with_["mlp_most_likely"][subset]["ade"] + 1e-6
    assert best["fde"] <= best["brier_min_fde"] <= best["fde"] + 1
  for method in without:  # the baseline changes no other row
    if method != "_meta":
      assert with_[method] == without[method]
  assert with_["_meta"]["baseline"]["epoch"] == load_baseline(tmp_path / "baseline").epoch
  assert without["_meta"]["baseline"] is None
  table = (tmp_path / "with" / "results.md").read_text()
  assert "| MLP, 3 heads (WTA): best of K |" in table
  # a baseline trained on another tokeniser's tokens is refused before anything is written
  bundle = load_baseline(tmp_path / "baseline")
  saved = bundle.fingerprint.to_dict()
  other = dataclasses.replace(
      bundle,
      fingerprint=ml_collections.FrozenConfigDict(
          {**saved, "tokenizer": {**saved["tokenizer"], "step": -1}}
      ),
  )
  monkeypatch.setattr(report_models, "load_baseline", lambda _: other)
  with pytest.raises(learned_baseline.IncompatibleBaselineError, match="step"):
    report.run(**kw, workdir=tmp_path / "refused", baseline_dir=tmp_path / "baseline")
  assert not (tmp_path / "refused").exists()


@pytest.mark.slow
def test_report_sampling_overrides_reach_the_predictor(runs, tmp_path):
  """evaluate.py --sampler/--steps: the report samples with the override, and its mean
  trajectory is the one a Predictor with that sampling gives."""
  scenarios = dataset.load_split(runs / "data", "test")
  scenarios = scenarios.take(balanced_indices(scenarios.label, 0, 6))
  results = report.run(
      tokenizer_dir=runs / "tokenizer",
      diffusion_dir=runs / "diffusion",
      data_dir=runs / "data",
      workdir=tmp_path / "eval_ddim2",
      max_scenarios=6,
      ddpm_scenarios=0,
      sampling_overrides={"sampler": "ddim", "steps": 2},
  )
  meta = json.loads((tmp_path / "eval_ddim2" / "metrics.json").read_text())["_meta"]
  assert (meta["sampling"]["sampler"], meta["sampling"]["steps"]) == ("ddim", 2)
  predictor = Predictor.load(runs / "tokenizer", runs / "diffusion")
  predictor = dataclasses.replace(
      predictor, sampling=dataclasses.replace(predictor.sampling, sampler="ddim", steps=2)
  )
  mean = predictor(scenarios, seed=0).prediction.mean
  ade = np.linalg.norm(np.asarray(mean) - scenarios.future, axis=-1).mean()
  np.testing.assert_allclose(results["cvmdx_mean"]["all"]["ade"], ade, rtol=1e-5)


def test_a_full_disk_leaves_the_previous_report_or_none(runs, tmp_path, monkeypatch):
  """ENOSPC while writing a figure: a fresh workdir is not left behind, an earlier
  report stays byte-identical; no temporaries either way."""
  kwargs = dict(
      tokenizer_dir=runs / "tokenizer",
      diffusion_dir=runs / "diffusion",
      data_dir=runs / "data",
      max_scenarios=6,
      ddpm_scenarios=0,
  )
  real = atomic.writing

  @contextlib.contextmanager
  def full_at_a_figure(path, mode="wb"):
    with real(path, mode) as f:
      if Path(path).name != "predictions_lcr.png":
        yield f
      else:
        yield types.SimpleNamespace(
            write=lambda data: (_ for _ in ()).throw(
                OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            )
        )

  fresh, kept = tmp_path / "fresh", tmp_path / "kept"
  report.run(workdir=kept, seed=1, **kwargs)
  before = {p.name: p.read_bytes() for p in kept.iterdir()}
  assert {"metrics.json", "results.md", "predictions_lcr.png", "checksums.json"} <= set(before)
  monkeypatch.setattr(atomic, "writing", full_at_a_figure)
  for workdir in (fresh, kept):
    with pytest.raises(OSError, match="No space left"):
      report.run(workdir=workdir, seed=0, **kwargs)
  assert not fresh.exists()  # the lock removes the directory it made, left empty
  assert {p.name: p.read_bytes() for p in kept.iterdir()} == before


def test_demo_reports_test_and_test_ood_in_one_schema(runs, tmp_path, monkeypatch, capsys):
  out = tmp_path / "demo"
  results = report.run_test_and_ood(
      tokenizer_dir=runs / "tokenizer",
      diffusion_dir=runs / "diffusion",
      data_dir=runs / "data",
      workdir=out,
      ddpm_scenarios=0,
      ood_ddpm_scenarios=0,
      max_scenarios=6,
  )
  assert set(results) == {"test", "test_ood"}
  test = json.loads((out / "metrics.json").read_text())
  ood = json.loads((out / "metrics_test_ood.json").read_text())
  assert (test["_meta"]["split"], ood["_meta"]["split"]) == ("test", "test_ood")
  schema = lambda m: {k: {s: set(r) for s, r in v.items()} for k, v in m.items() if k != "_meta"}
  assert schema(test) == schema(ood)
  assert test["cv"]["all"]["num_scenarios"] == ood["cv"]["all"]["num_scenarios"] == 6
  assert ood["_meta"]["dataset_id"] == test["_meta"]["dataset_id"]
  assert 0 <= ood["cvmdx_mean"]["all"]["out_of_distribution"] <= 1
  assert "| Constant velocity |" in (out / "results_test_ood.md").read_text()
  assert (out / "kl_vs_usage_test_ood.png").is_file()
  # the memory handed back between the splits changes no number: test_ood alone is the same
  alone = report.run(
      tokenizer_dir=runs / "tokenizer",
      diffusion_dir=runs / "diffusion",
      data_dir=runs / "data",
      workdir=tmp_path / "alone",
      split="test_ood",
      ddpm_scenarios=0,
      max_scenarios=6,
  )
  same = lambda metrics: json.dumps(metrics, sort_keys=True)  # NaN (too few to rank) as NaN
  assert same(alone) == same(results["test_ood"])
  # a dataset without test_ood (highD, cvmd_mat): the test report only, and a note
  monkeypatch.setattr(report.dataset_lib, "split_names", lambda _: ["train", "val", "test"])
  calls = []
  monkeypatch.setattr(
      report.dataset_lib, "load_balanced", lambda data_dir, split, *_: calls.append(split)
  )
  monkeypatch.setattr(report.report_models, "load", lambda **_: None)
  monkeypatch.setattr(
      report, "evaluate", lambda *_, **kw: types.SimpleNamespace(results=kw["split"])
  )
  monkeypatch.setattr(report.files, "write", lambda *_: None)
  assert list(
      report.run_test_and_ood(
          tokenizer_dir=None,
          diffusion_dir=None,
          data_dir="d",
          workdir=out,
          ddpm_scenarios=0,
          ood_ddpm_scenarios=0,
      )
  ) == ["test"]
  assert calls == ["test"] and "no test_ood split" in capsys.readouterr().out


def test_non_finite_predictions_stop_the_evaluation(runs, tmp_path, monkeypatch):
  predict = Predictor.__call__

  def nan_in_scenario_1(self, scenarios, seed=0):
    out = predict(self, scenarios, seed)
    traj = out.prediction.trajectories.copy()
    traj[1, 0, 5, 0] = np.nan
    return dataclasses.replace(
        out, prediction=dataclasses.replace(out.prediction, trajectories=traj)
    )

  monkeypatch.setattr(Predictor, "__call__", nan_in_scenario_1)
  with pytest.raises(
      scoring.NonFinitePredictionError,
      match=r"non-finite predictions for 1 of 6 scenarios: #1 \(recording",
  ):
    report.run(
        tokenizer_dir=runs / "tokenizer",
        diffusion_dir=runs / "diffusion",
        data_dir=runs / "data",
        workdir=tmp_path / "eval",
        max_scenarios=6,
        ddpm_scenarios=0,
    )
  assert not (tmp_path / "eval").exists()


def test_predictor_flags_scenarios_beyond_the_training_range(runs):
  predictor = Predictor.load(runs / "tokenizer", runs / "diffusion")
  with np.load(runs / "tokenizer" / "tokens" / "train.npz") as train:
    assert predictor.delta_limit == pytest.approx(float(train["delta"].max()))
  scenarios = dataset.load_split(runs / "data", "test").take(np.arange(6))
  xi = scenarios.xi.copy()
  xi[2] *= 1e4  # positions and velocities far outside any training scenario
  far = scenarios.__class__(**{**scenarios.as_dict(), "xi": xi})
  with pytest.warns(OutOfDistributionWarning, match=r"training range .*scenarios \[.*2"):
    out = predictor(far, seed=0)
  assert out.out_of_distribution.dtype == bool and out.out_of_distribution.shape == (6,)
  assert out.out_of_distribution[2] and out.delta[2] > predictor.delta_limit
  np.testing.assert_array_equal(out.out_of_distribution, out.delta > predictor.delta_limit)


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


@pytest.mark.slow
def test_load_denoiser_restores_the_ema_params_alone(runs):
  denoiser = load_denoiser(runs / "diffusion")
  # reference: the whole train state, restored with the trainer's init_fn
  config = DiffusionRunConfig.from_config(
      json.loads((runs / "diffusion" / "config.json").read_text())
  )
  assert config == denoiser.config
  _, init_fn, _ = diffusion.init_and_step(config, total_steps=1)
  state, fingerprint = toy.restore(runs / "diffusion", init_fn)
  jax.tree.map(np.testing.assert_array_equal, denoiser.params, state["ema_params"])
  assert denoiser.fingerprint.to_dict()["dataset_id"] == fingerprint["dataset_id"]
  x, t, q = jnp.ones((2, 125, 2)) * 0.3, jnp.array([10, 900]), jnp.array([0, denoiser.null_token])
  np.testing.assert_array_equal(
      denoiser.apply(x, t, q),
      unet1d.apply_unet(unet1d.make_graphdef(denoiser.unet), state["ema_params"], x, t, q),
  )


def test_predictor_refuses_bad_scenarios(runs):
  scenarios = dataset.load_split(runs / "data", "test").take(np.arange(2))
  predictor = Predictor.load(runs / "tokenizer", runs / "diffusion")
  xi = scenarios.xi.copy()
  xi[1, 0, 3, 0] = np.nan
  with pytest.raises(ValueError, match="'xi' holds NaN/inf \\(scenario 1\\)"):
    predictor(scenarios.__class__(**{**scenarios.as_dict(), "xi": xi}))
  with pytest.raises(ValueError, match="'xi' has shape"):
    predictor(scenarios.__class__(**{**scenarios.as_dict(), "xi": scenarios.xi[:, :, :50]}))
  for seed in (2**32, -1, True):
    with pytest.raises(ValueError, match=r"^seed="):
      predictor(scenarios, seed=seed)
  mask = scenarios.mask.copy()
  mask[1, 0, -1] = False
  with pytest.raises(ValueError, match="ego absent at t0.*scenario 1"):
    predictor(scenarios.__class__(**{**scenarios.as_dict(), "mask": mask}))


def test_runs_that_do_not_belong_together_are_refused(runs, tmp_path):
  other = tokenizer_config.get_config("tiny,q=5")
  other.data_dir = str(runs / "data")
  fixtures_runs.train_tokenizer(other, tmp_path / "other_tokenizer")
  with pytest.raises(IncompatibleRunsError, match="5"):
    Predictor.load(tmp_path / "other_tokenizer", runs / "diffusion")


@pytest.mark.slow
def test_ego_conditioned_run_trains_loads_and_predicts(runs, tmp_path):
  diff = diffusion_config.get_config("tiny")
  diff.data_dir, diff.tokenizer_dir = str(runs / "data"), str(runs / "tokenizer")
  diff.diffusion.conditioning = "ego_film_residual"
  data, *_ = diffusion.training_data(DiffusionRunConfig.from_config(diff))
  train = dataset.load_split(runs / "data", "train")
  ego = np.asarray(ego_motion.ego_features(train.xi, train.mask))
  base = np.asarray(ego_motion.residual_controls(ego, diff.diffusion.residual_decay_s))
  scale = np.asarray(diff.diffusion.control_scale)
  np.testing.assert_allclose(data["ego"], ego)
  np.testing.assert_allclose(data["x0"], np.clip((train.controls - base) / scale, -1, 1), atol=1e-6)
  fixtures_runs.train_diffusion(diff, tmp_path / "ego")
  predictor = Predictor.load(runs / "tokenizer", tmp_path / "ego")
  assert predictor.denoiser.config.diffusion.conditioning == "ego_film_residual"
  assert predictor.denoiser.unet.cond_dim == ego_motion.NUM_FEATURES
  scenarios = dataset.load_split(runs / "data", "test").take(np.arange(5))
  a = predictor(scenarios, seed=1)
  b = Predictor.load(runs / "tokenizer", tmp_path / "ego", chunk_size=2)(scenarios, seed=1)
  np.testing.assert_allclose(a.prediction.trajectories, b.prediction.trajectories, atol=1e-4)
  assert a.prediction.trajectories.shape == (5, 9, 125, 2)
  with pytest.raises(ValueError, match="diffusion.conditioning"):
    diff.diffusion.conditioning = "ego"
    fixtures_runs.train_diffusion(diff, tmp_path / "bad")
  assert not (tmp_path / "bad").exists()


def test_denoiser_of_another_feature_count_is_refused(runs, tmp_path, monkeypatch):
  """A run trained when ego_motion had another feature table (13 before the neighbours)
  is refused by name instead of failing inside the U-Net."""
  diff = diffusion_config.get_config("tiny")
  diff.data_dir, diff.tokenizer_dir = str(runs / "data"), str(runs / "tokenizer")
  diff.diffusion.conditioning = "ego_film"
  fixtures_runs.train_diffusion(diff, tmp_path / "ego")
  monkeypatch.setattr(ego_motion, "NUM_FEATURES", ego_motion.NUM_FEATURES + 1)
  with pytest.raises(checkpointing.CheckpointMismatchError, match="ego-motion features"):
    Predictor.load(runs / "tokenizer", tmp_path / "ego")


def test_unknown_split_raises_and_writes_nothing(runs, tmp_path):
  out = tmp_path / "eval"
  with pytest.raises(ValueError, match="validation"):
    report.run(
        tokenizer_dir=runs / "tokenizer",
        diffusion_dir=runs / "diffusion",
        data_dir=runs / "data",
        workdir=out,
        split="validation",
    )
  assert not out.exists()


@pytest.mark.slow
def test_codebook_ablation_script(runs, tmp_path):
  out = tmp_path / "ablation"
  proc = subprocess.run(
      [
          sys.executable,
          str(REPO / "experiments" / "ablate_codebook.py"),
          f"--data_dir={runs / 'data'}",
          f"--workdir={out}",
          "--codebook_sizes=4,6",
          "--tokenizer_preset=tiny",
          "--diffusion_preset=tiny",
          "--max_scenarios=12",
      ],
      env=environ(),
      capture_output=True,
      text=True,
      timeout=600,
  )
  assert proc.returncode == 0, proc.stderr[-3000:]
  rows = [
      line for line in (out / "ablation.md").read_text().splitlines() if line.startswith("| cvq |")
  ]
  assert [r.split("|")[2].strip() for r in rows] == ["4", "6"]
  saved = json.loads((out / "ablation.json").read_text())
  assert saved["cvq_q6"]["cvmdx_mean"]["all"]["num_scenarios"] == 12


@pytest.mark.slow
def test_codebook_health_script(runs, tmp_path):
  out = tmp_path / "health"
  proc = subprocess.run(
      [
          sys.executable,
          str(REPO / "experiments" / "codebook_health.py"),
          "--config=configs/tokenizer.py:tiny",
          f"--config.data_dir={runs / 'data'}",
          f"--workdir={out}",
          "--codebook_sizes=4",
      ],
      cwd=REPO,
      env=environ(),
      capture_output=True,
      text=True,
      timeout=600,
  )
  assert proc.returncode == 0, proc.stderr[-3000:]
  lines = (out / "codebook_health.md").read_text().splitlines()
  cells = {line.split("|")[2].strip(): line.split("|")[1:-1] for line in lines[2:]}
  assert set(cells) == {"constant velocity", "cvq", "vq"}
  test = dataset.load_split(runs / "data", "test")
  cv = test.xi[:, 0, -1, None, 2:4] * (0.04 * np.arange(1, 126))[None, :, None]
  err = np.linalg.norm(cv - test.future, axis=-1)
  np.testing.assert_allclose(
      [float(v) for v in cells["constant velocity"][-2:]],
      [err.mean(), err[:, -1].mean()],
      atol=1e-3,
  )
  for kind in ("cvq", "vq"):
    assert all(np.isfinite(float(v)) for v in cells[kind][-2:])


def test_imported_official_checkpoint_pairs_with_a_tokenizer(runs, tmp_path, monkeypatch):
  from tests.models import official_fixture

  checkpoint = tmp_path / "ema_0.9999_000100.pt"
  official_fixture.write_pt(
      checkpoint, official_fixture.state_dict(np.random.default_rng(0), 8), monkeypatch
  )  # Q = 8, the tiny tokeniser's codebook size
  proc = subprocess.run(
      [
          sys.executable,
          str(REPO / "experiments" / "import_official.py"),
          f"--checkpoint={checkpoint}",
          f"--workdir={tmp_path / 'official'}",
          f"--tokenizer_dir={runs / 'tokenizer'}",
      ],
      env=environ(),
      capture_output=True,
      text=True,
      timeout=600,
  )
  assert proc.returncode == 0, proc.stderr[-3000:]
  predictor = Predictor.load(runs / "tokenizer", tmp_path / "official")
  assert predictor.sampling.mode == "official" and predictor.denoiser.unet.num_tokens == 8
  out = predictor(dataset.load_split(runs / "data", "test").take(np.arange(2)), seed=0)
  assert out.prediction.trajectories.shape == (2, 9, 125, 2)
  assert np.isfinite(out.prediction.trajectories).all()


@pytest.mark.slow
def test_class_weights_weight_each_training_scenario_by_its_class(runs):
  diff = diffusion_config.get_config("tiny")
  diff.data_dir, diff.tokenizer_dir = str(runs / "data"), str(runs / "tokenizer")
  plain, num_tokens, dataset_id, meta = diffusion.training_data(
      DiffusionRunConfig.from_config(diff)
  )
  assert "class_weight" not in plain  # the paper's balanced classes: no extra array
  fingerprint = fingerprints.diffusion(
      DiffusionRunConfig.from_config(diff).with_tokens(num_tokens), dataset_id, meta
  )
  assert fingerprint["class_weights"] == [1.0, 1.0, 1.0]
  diff.diffusion.class_weights = (3.0, 1.0, 0.5)
  config = DiffusionRunConfig.from_config(diff).with_tokens(num_tokens)
  data, *_ = diffusion.training_data(config)
  labels = dataset.load_split(runs / "data", "train").label
  np.testing.assert_array_equal(data["class_weight"], np.array([3.0, 1.0, 0.5])[labels])
  assert fingerprints.diffusion(config, dataset_id, meta)["class_weights"] == [3.0, 1.0, 0.5]
  # the step multiplies the loop's padding weight by the class weight: a zero class weight
  # removes a row from the loss exactly as padding does
  _, init_fn, step_fn = diffusion.init_and_step(config, total_steps=10)
  state = init_fn(jax.random.key(0))
  rows = np.arange(8)
  batch = {"x0": jnp.asarray(data["x0"][rows]), "q": jnp.asarray(data["q"][rows])}
  keep = jnp.asarray(np.arange(8) % 3 != 0, jnp.float32)
  step = jax.jit(step_fn)
  _, padded = step(state, {**batch, "weight": keep}, jax.random.key(1))
  _, weighted = step(
      state, {**batch, "weight": jnp.ones(8), "class_weight": keep}, jax.random.key(1)
  )
  _, unweighted = step(state, {**batch, "weight": jnp.ones(8)}, jax.random.key(1))
  np.testing.assert_allclose(weighted["loss"], padded["loss"], rtol=1e-6)
  assert abs(float(weighted["loss"]) - float(unweighted["loss"])) > 1e-6
  for bad in [(1.0, 1.0), (1.0, 0.0, 1.0), (1.0, float("nan"), 1.0)]:
    diff.diffusion.class_weights = bad
    with pytest.raises(ValueError, match="diffusion.class_weights"):
      DiffusionRunConfig.from_config(diff)


def _distill(
    teacher_dir, workdir, steps, guided_progressive=False, teacher_substeps=2, init_dir=""
):
  config = distill_config.get_config("tiny")
  config.teacher_dir, config.steps = str(teacher_dir), steps
  config.guided_progressive, config.teacher_substeps = guided_progressive, teacher_substeps
  config.init_dir = str(init_dir)
  return distill.train(DistillRunConfig.from_config(config), workdir)


@pytest.mark.slow  # trains five tiny students (~150 s); tests/train/test_distill.py covers a stage
def test_distilled_students_load_predict_and_refuse_other_teachers(runs, tmp_path, monkeypatch):
  scenarios = dataset.load_split(runs / "data", "test").take(np.arange(4))
  teacher = load_denoiser(runs / "diffusion")
  _distill(runs / "diffusion", tmp_path / "guidance", 4)
  _distill(tmp_path / "guidance", tmp_path / "progressive", 2)
  _distill(runs / "diffusion", tmp_path / "direct", 2, guided_progressive=True)
  _distill(
      runs / "diffusion", tmp_path / "direct_k5", 2, guided_progressive=True, teacher_substeps=5
  )
  for name, steps, progressive in (
      ("guidance", 4, False),
      ("progressive", 2, True),
      ("direct", 2, True),
      ("direct_k5", 2, True),
  ):
    predictor = Predictor.load(runs / "tokenizer", tmp_path / name)
    student = predictor.denoiser.config
    assert (predictor.sampling.sampler, predictor.sampling.steps) == ("distilled", steps)
    assert predictor.denoiser.progressive == progressive
    assert student.diffusion.guidance_input and student.model.cond_dim == 1
    assert student.model.num_tokens == teacher.config.model.num_tokens
    a, b = predictor(scenarios, seed=1), predictor(scenarios, seed=1)
    np.testing.assert_array_equal(a.prediction.trajectories, b.prediction.trajectories)
    assert a.prediction.trajectories.shape == (4, 9, 125, 2)
    assert np.isfinite(a.prediction.trajectories).all()
  # a progressive student knows only its own steps: the DDPM row needs the guided denoiser
  common = dict(
      tokenizer_dir=runs / "tokenizer",
      diffusion_dir=tmp_path / "progressive",
      data_dir=runs / "data",
      max_scenarios=6,
      ddpm_scenarios=3,
      figures_per_class=1,
  )
  alone = report.run(workdir=tmp_path / "alone", **common)
  paired = report.run(workdir=tmp_path / "paired", ddpm_diffusion_dir=runs / "diffusion", **common)
  assert "ddpm_single" not in alone and paired["ddpm_single"]["all"]["num_scenarios"] == 3
  meta = json.loads((tmp_path / "paired" / "metrics.json").read_text())["_meta"]
  assert meta["sampling"]["sampler"] == "distilled"
  assert meta["ddpm_diffusion_dir"] == str(runs / "diffusion")
  # a progressive student for 2 steps teaches one for 1 step, not another for 2
  with pytest.raises(distill.TeacherMismatchError, match="not steps=2"):
    _distill(tmp_path / "progressive", tmp_path / "again", 2)
  with pytest.raises(distill.TeacherMismatchError, match="teacher_substeps=3 .* 0.666667 steps"):
    _distill(tmp_path / "progressive", tmp_path / "again", 1, teacher_substeps=3)
  # k teacher steps a student step: the fingerprint names k
  recorded = lambda d: load_denoiser(tmp_path / d).fingerprint.to_dict()["distill"]
  assert recorded("direct_k5")["teacher_substeps"] == 5
  assert recorded("direct")["teacher_substeps"] == 2
  for teacher_dir in ("direct", "guidance"):  # guided_progressive needs the guided pair
    with pytest.raises(distill.TeacherMismatchError, match="not a guided denoiser"):
      _distill(tmp_path / teacher_dir, tmp_path / "again", 1, guided_progressive=True)
  assert not (tmp_path / "again").exists()
  # the student of one stage teaches the next halving, as a progressive student does
  _distill(tmp_path / "direct", tmp_path / "halved", 1)
  assert Predictor.load(runs / "tokenizer", tmp_path / "halved").sampling.steps == 1
  # or a one-step student of the guided pair starts from that student's parameters
  _distill(runs / "diffusion", tmp_path / "one", 1, True, 4, init_dir=tmp_path / "direct")
  start_id = identity.content_id(load_denoiser(tmp_path / "direct").params)
  assert recorded("one")["init"] == start_id and "init" not in recorded("direct")
  with pytest.raises(distill.TeacherMismatchError, match="init_dir: .* not a distilled run"):
    _distill(runs / "diffusion", tmp_path / "again", 1, True, 4, init_dir=runs / "diffusion")
  assert not (tmp_path / "again").exists()
  # a guided_progressive run directory is not resumed as a guidance run of the same steps
  with pytest.raises(checkpointing.CheckpointMismatchError):
    _distill(runs / "diffusion", tmp_path / "direct", 2)
  # the distilled sampler needs a student; a student has no guided pair for the official mode
  with pytest.raises(ValueError, match="'distilled' needs a distilled denoiser"):
    Predictor.load(
        runs / "tokenizer",
        runs / "diffusion",
        dataclasses.replace(teacher.config.sampling, sampler="distilled"),
    )
  with pytest.raises(ValueError, match="'official'"):
    Predictor.load(
        runs / "tokenizer",
        tmp_path / "guidance",
        dataclasses.replace(teacher.config.sampling, sampler="ddim", mode="official"),
    )
  # resuming with a teacher of other weights is refused, naming the teacher's params id
  load = load_denoiser
  other = lambda d: dataclasses.replace(
      load(d), params=jax.tree.map(lambda p: p + 1e-3, load(d).params)
  )
  monkeypatch.setattr(distill, "load_denoiser", other)
  with pytest.raises(checkpointing.CheckpointMismatchError, match="teacher.params_id"):
    _distill(runs / "diffusion", tmp_path / "guidance", 4)


@pytest.mark.slow
def test_a_stopped_distillation_resumes_bit_identically(runs, tmp_path):
  """The demo's one-stage run, stopped after its first epoch's checkpoint (the second one
  removed, as a kill before it was written leaves the directory), then rerun."""
  config = distill_config.get_config("tiny")
  config.teacher_dir, config.train.num_epochs = str(runs / "diffusion"), 2
  config.steps, config.guided_progressive = 2, True
  whole = distill.train(DistillRunConfig.from_config(config), tmp_path / "whole")
  shutil.copytree(tmp_path / "whole", tmp_path / "stopped")
  shutil.rmtree(tmp_path / "stopped" / "checkpoints" / "2")
  resumed = distill.train(DistillRunConfig.from_config(config), tmp_path / "stopped")
  jax.tree.map(np.testing.assert_array_equal, whole["ema_params"], resumed["ema_params"])
  assert int(resumed["step"]) == int(whole["step"])
  # resumed, not restarted: epoch 1's line (with its wall time) is kept, epoch 2's rewritten
  lines = lambda d: (tmp_path / d / "metrics.jsonl").read_text().splitlines()
  assert len(lines("stopped")) == 2 and lines("stopped")[0] == lines("whole")[0]


@pytest.mark.slow
def test_intent_conditioned_run_trains_distills_and_predicts(runs, tmp_path):
  diff = diffusion_config.get_config("tiny")
  diff.data_dir, diff.tokenizer_dir = str(runs / "data"), str(runs / "tokenizer")
  diff.diffusion.conditioning = "ego_film_residual"
  diff.diffusion.intent_conditioning = True
  data, *_ = diffusion.training_data(DiffusionRunConfig.from_config(diff))
  train = dataset.load_split(runs / "data", "train")
  ego = np.asarray(ego_motion.ego_features(train.xi, train.mask))
  np.testing.assert_allclose(data["ego"], np.concatenate([ego, np.eye(3)[train.label]], -1))
  np.testing.assert_array_equal(data["label"], train.label)
  fixtures_runs.train_diffusion(diff, tmp_path / "intent")
  scenarios = dataset.load_split(runs / "data", "test").take(np.arange(4))
  predictor = Predictor.load(runs / "tokenizer", tmp_path / "intent")
  assert predictor.denoiser.unet.num_intents == 3
  a, b = predictor(scenarios, seed=1), predictor(scenarios, seed=1)
  np.testing.assert_array_equal(a.prediction.trajectories, b.prediction.trajectories)
  assert a.prediction.trajectories.shape == (4, 9, 125, 2)
  _distill(tmp_path / "intent", tmp_path / "student", 2, guided_progressive=True)
  student = Predictor.load(runs / "tokenizer", tmp_path / "student")
  assert student.denoiser.unet.num_intents == 3 and student.denoiser.config.diffusion.guidance_input
  out = student(scenarios, seed=1)
  assert out.prediction.trajectories.shape == (4, 9, 125, 2)
  assert np.isfinite(out.prediction.trajectories).all()


def test_a_road_never_seen_as_a_test_only_highd_dataset(runs, tmp_path):
  """The held-out road's recording read as raw highD into a test-only dataset (docs/usage.md,
  "A trained model on a road it never saw") holds the same scenarios as the pipeline's
  test_ood split, and the trained runs score it like that split."""
  from cvmdx_jax.data import sumo_plan

  ood_ids = sumo_plan.split_ids(dataset_config.get_config("tiny").sumo)["test_ood"]
  config = dataset_config.get_config("tiny")
  config.source, config.highd_dir = "highd", str(runs / "data" / "recordings")
  config.splits.train, config.splits.val, config.splits.test = (), (), tuple(ood_ids)
  road = dataset.build(config, tmp_path / "road")
  assert list(road) == ["test"]
  ood = dataset.load_split(runs / "data", "test_ood")
  for field in ("xi", "mask", "future", "label", "recording_id", "frame"):
    np.testing.assert_array_equal(getattr(road["test"], field), getattr(ood, field))
  kw = dict(
      tokenizer_dir=runs / "tokenizer",
      diffusion_dir=runs / "diffusion",
      max_scenarios=12,
      ddpm_scenarios=0,
  )
  on_road = report.run(**kw, data_dir=tmp_path / "road", split="test", workdir=tmp_path / "a")
  as_ood = report.run(**kw, data_dir=runs / "data", split="test_ood", workdir=tmp_path / "b")
  for method in ("cv", "cvmdx_mean", "cvmdx_best_of_k"):
    assert on_road[method]["all"]["ade"] == as_ood[method]["all"]["ade"]
    assert on_road[method]["all"]["num_scenarios"] == 12
