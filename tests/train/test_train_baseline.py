"""Training of the multiple-choice baseline on a synthetic three-mode dataset: the loss
falls, the epoch chosen on val is the val curve's minimum, a stopped run resumes
bit-identically, the seed fixes the result, and a bad setting is refused."""

import json

import jax
import numpy as np
import pytest

from configs import baseline as baseline_config
from cvmdx_jax.config.fields import ConfigFieldError
from cvmdx_jax.config.runs import BaselineRunConfig
from cvmdx_jax.inference.bundles import load_baseline
from cvmdx_jax.runs import layout
from cvmdx_jax.storage.checkpointing import CheckpointMismatchError
from cvmdx_jax.train import baseline
from tests.train import baseline_data


@pytest.fixture(scope="module")
def dirs(tmp_path_factory):
  return baseline_data.written(tmp_path_factory.mktemp("baseline"))


def _config(dirs, **train):
  return baseline_data.run_config(baseline_config.get_config("tiny"), dirs, **train)


def _train(config, workdir):
  return baseline.train(BaselineRunConfig.from_config(config), workdir)


def _params(workdir):
  return jax.tree.map(np.asarray, load_baseline(workdir).params)


@pytest.fixture(scope="module")
def trained(dirs):
  workdir = dirs / "run"
  _train(_config(dirs), workdir)
  return workdir


def test_loss_falls_and_the_val_minimum_is_kept(trained):
  curve = baseline_data.curve(trained)
  assert [r["epoch"] for r in curve] == [1, 2, 3, 4]
  assert curve[-1]["loss"] < curve[0]["loss"]
  assert curve[-1]["val_min_ade"] < curve[0]["val_min_ade"]
  scores = [r["val_min_ade"] for r in curve]
  chosen = load_baseline(trained)
  assert chosen.epoch == int(np.argmin(scores)) + 1 == curve[-1]["best_epoch"]
  np.testing.assert_allclose(curve[-1]["best_val_score"], min(scores), rtol=1e-6)
  assert sum(curve[-1]["val_head_share"]) == pytest.approx(1.0)
  # best of K <= most likely and <= the probability-weighted mean, by construction
  for r in curve:
    assert r["val_min_ade"] <= min(r["val_ml_ade"], r["val_mean_ade"]) + 1e-6
  assert chosen.fingerprint.to_dict()["tokenizer"] == baseline_data.TOKENIZER_CHECKPOINT
  saved = json.loads((trained / layout.CONFIG_JSON).read_text())
  assert saved["model"]["num_tokens"] == baseline_data.NUM_TOKENS == chosen.config.model.num_tokens


def test_stopped_run_resumes_bit_identically(dirs, trained):
  baseline_data.assert_resumes_bit_identically(
      trained, dirs / "resumed", lambda workdir: _train(_config(dirs), workdir), _params
  )


def test_the_seed_fixes_the_result(dirs, trained):
  _train(_config(dirs), dirs / "again")
  jax.tree.map(np.testing.assert_array_equal, _params(dirs / "again"), _params(trained))
  other = _config(dirs)
  other.seed = 1
  _train(other, dirs / "seed1")
  baseline_data.assert_every_leaf_differs(_params(trained), _params(dirs / "seed1"))


def test_another_setting_in_the_same_workdir_is_refused(dirs):
  workdir = dirs / "refuse"
  _train(_config(dirs, num_epochs=1), workdir)
  before = (workdir / layout.CONFIG_JSON).read_bytes()
  config = _config(dirs, num_epochs=1)
  config.model.hidden = (24,)
  with pytest.raises(CheckpointMismatchError):
    _train(config, workdir)
  assert (workdir / layout.CONFIG_JSON).read_bytes() == before


def test_bad_settings_are_refused_naming_the_field(dirs):
  for field, value in (
      ("select_metric", "accuracy"),
      ("end_lr_fraction", 1.5),
      ("warmup_steps", -1),
  ):
    with pytest.raises(ConfigFieldError, match=f"train.{field}"):
      BaselineRunConfig.from_config(_config(dirs, **{field: value}))
  config = _config(dirs)
  config.loss.cls_weight = -1.0
  with pytest.raises(ConfigFieldError, match="loss.cls_weight"):
    BaselineRunConfig.from_config(config)
