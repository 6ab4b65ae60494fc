"""Training of the mixture density baseline on the synthetic three-mode dataset of the
multiple-choice baseline's tests: the val NLL falls through a warm-up epoch, the chosen
epoch is the val curve's minimum, the loaded model is that epoch's mixture, a stopped run
resumes bit-identically, the seed fixes the result, and bad settings are refused."""

import json

import jax
import numpy as np
import pytest

from configs import mdn as mdn_config
from cvmdx_jax.config.fields import ConfigFieldError
from cvmdx_jax.config.mdn import MDNRunConfig
from cvmdx_jax.data import dataset as dataset_lib
from cvmdx_jax.inference import mdn_baseline
from cvmdx_jax.inference.bundles import load_baseline
from cvmdx_jax.models import mdn
from cvmdx_jax.runs import layout
from cvmdx_jax.runs import tokens as tokens_lib
from cvmdx_jax.storage.checkpointing import CheckpointMismatchError
from cvmdx_jax.train import mdn as mdn_train
from tests.train import baseline_data


@pytest.fixture(scope="module")
def dirs(tmp_path_factory):
  return baseline_data.written(tmp_path_factory.mktemp("mdn"))


def _config(dirs, **train):
  config = baseline_data.run_config(mdn_config.get_config("tiny"), dirs, **train)
  config.loss.warmup_epochs = 1
  return config


def _train(config, workdir):
  return mdn_train.train(MDNRunConfig.from_config(config), workdir)


def _params(workdir):
  return jax.tree.map(np.asarray, mdn_baseline.load_mdn(workdir).params)


@pytest.fixture(scope="module")
def trained(dirs):
  workdir = dirs / "run"
  _train(_config(dirs), workdir)
  return workdir


def test_val_nll_falls_and_the_val_minimum_is_kept(dirs, trained):
  curve = baseline_data.curve(trained)
  assert [r["epoch"] for r in curve] == [1, 2, 3, 4]
  assert curve[-1]["val_nll"] < curve[0]["val_nll"]
  scores = [r["val_loss"] for r in curve]
  chosen = mdn_baseline.load_mdn(trained)
  assert chosen.epoch == int(np.argmin(scores)) + 1 == curve[-1]["best_epoch"]
  np.testing.assert_allclose(curve[-1]["best_val_score"], min(scores), rtol=1e-6)
  for r in curve:  # the scenario NLL is the loss over the 250 coordinates
    np.testing.assert_allclose(r["val_nll"], 250 * r["val_loss"], rtol=1e-5)
    assert r["val_min_ade"] <= min(r["val_ml_ade"], r["val_mean_ade"]) + 1e-6
  assert chosen.fingerprint.to_dict()["tokenizer"] == baseline_data.TOKENIZER_CHECKPOINT
  saved = json.loads((trained / layout.CONFIG_JSON).read_text())
  assert saved["model"]["num_tokens"] == baseline_data.NUM_TOKENS

  # the loaded model's mixture on val has the chosen epoch's val NLL
  val = dataset_lib.load_split(dirs / "data", "val")
  toks, _ = tokens_lib.load_tokens(tokens_lib.tokens_path(dirs / "tokenizer", "val"))
  mixture = chosen(toks.q, toks.delta, val.xi, val.mask, val.v0, val.psi0)
  assert mixture.means.shape == mixture.stds.shape == (len(val), 3, 125, 2)
  np.testing.assert_allclose(mixture.weights.sum(-1), 1.0, rtol=1e-6)
  assert np.all(mixture.stds >= np.float32(chosen.config.model.std_floor_m))
  nll = -mdn.log_likelihood(mixture.means, mixture.stds, np.log(mixture.weights), val.future)
  best = curve[chosen.epoch - 1]
  np.testing.assert_allclose(np.mean(nll), best["val_nll"], rtol=1e-4)


def test_stopped_run_resumes_bit_identically(dirs, trained):
  baseline_data.assert_resumes_bit_identically(
      trained, dirs / "resumed", lambda workdir: _train(_config(dirs), workdir), _params
  )


def test_another_seed_gives_other_parameters(dirs, trained):
  other = _config(dirs, num_epochs=2)
  other.seed = 1
  _train(other, dirs / "seed1")
  baseline_data.assert_every_leaf_differs(_params(trained), _params(dirs / "seed1"))


def test_a_multiple_choice_loader_refuses_the_run(trained):
  with pytest.raises(CheckpointMismatchError, match="config.json"):
    load_baseline(trained)


def test_bad_settings_are_refused_naming_the_field(dirs):
  for section, field, value in (
      ("loss", "warmup_epochs", -1),
      ("model", "std_floor_m", 0.0),
      ("train", "select_metric", "nll_5s"),
  ):
    config = _config(dirs)
    config[section][field] = value
    with pytest.raises(ConfigFieldError, match=f"{section}.{field}"):
      MDNRunConfig.from_config(config)
