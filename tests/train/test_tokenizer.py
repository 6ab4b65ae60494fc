"""The tokeniser trainer's smoke run, load_tokenizer/tokenize, saved tokens, mismatch errors."""

import json

import jax
import numpy as np
import pytest
import scipy.stats

from configs import common
from configs import tokenizer as tokenizer_config
from cvmdx_jax.config.runs import TokenizerRunConfig
from cvmdx_jax.inference.bundles import TokenizerBundle, load_tokenizer
from cvmdx_jax.runs import tokens as tokens_lib
from cvmdx_jax.storage.checkpointing import CheckpointMismatchError
from cvmdx_jax.train import tokenizer as train_tok


@pytest.fixture(scope="module")
def trained(tmp_path_factory, scenarios_factory):
  workdir = tmp_path_factory.mktemp("tok")
  config = tokenizer_config.get_config("tiny")
  config.train.num_epochs = 2
  config = TokenizerRunConfig.from_config(config)
  splits = {"train": scenarios_factory(24, 0), "test": scenarios_factory(10, 1)}
  train_tok.train(config, workdir, splits=splits)
  return workdir, config, splits


def test_smoke_run_writes_metrics_and_tokens(trained):
  workdir, config, splits = trained
  lines = [json.loads(x) for x in (workdir / "metrics.jsonl").read_text().splitlines()]
  assert [x["epoch"] for x in lines] == [1, 2]
  for key in (
      "reconstruction",
      "codebook",
      "commitment",
      "classification",
      "accuracy",
      "entries_in_use",
      "perplexity",
      "train_accuracy",
  ):
    assert np.isfinite(lines[-1][key]), key
  train_tokens, meta = tokens_lib.load_tokens(tokens_lib.tokens_path(workdir, "train"))
  q = train_tokens.q
  assert lines[-1]["entries_in_use"] == len(np.unique(q))
  np.testing.assert_allclose(
      lines[-1]["perplexity"], np.exp(scipy.stats.entropy(np.bincount(q))), rtol=1e-4
  )
  assert meta["split"] == "train" and meta["codebook_size"] == config.model.quantizer.codebook_size
  assert train_tokens.z_hat.shape == (24, config.model.encoder.latent_dim)
  assert np.all(train_tokens.delta >= 0)


def test_load_tokenizer_reproduces_saved_tokens(trained):
  workdir, _, splits = trained
  bundle = load_tokenizer(workdir)
  test = splits["test"]
  q, z_hat, delta = jax.jit(TokenizerBundle.tokenize)(bundle, test.xi, test.mask)
  saved, _ = tokens_lib.load_tokens(tokens_lib.tokens_path(workdir, "test"))
  np.testing.assert_array_equal(q, saved.q)
  np.testing.assert_allclose(z_hat, saved.z_hat, atol=1e-5)
  np.testing.assert_allclose(delta, saved.delta, rtol=1e-4, atol=1e-5)


def test_tokens_from_another_dataset_are_refused(trained):
  workdir, _, _ = trained
  path = tokens_lib.tokens_path(workdir, "test")
  _, meta = tokens_lib.load_tokens(path, num_scenarios=10)
  tokens_lib.load_tokens(path, dataset_id=meta["dataset_id"])
  with pytest.raises(tokens_lib.TokensMismatchError, match="other-data"):
    tokens_lib.load_tokens(path, dataset_id="other-data")
  with pytest.raises(tokens_lib.TokensMismatchError, match="11"):
    tokens_lib.load_tokens(path, num_scenarios=11)


def test_checkpoint_with_other_codebook_size_is_refused(trained):
  workdir, config, splits = trained
  other = tokenizer_config.get_config("tiny")
  other.quantizer.codebook_size = config.model.quantizer.codebook_size + 1
  with pytest.raises(CheckpointMismatchError, match="codebook_size"):
    train_tok.train(TokenizerRunConfig.from_config(other), workdir, splits=splits)


def test_bad_dataset_and_missing_files_give_clear_errors(trained, tmp_path):
  _, config, splits = trained
  bad = splits["train"].take(np.arange(24))
  object.__setattr__(bad, "xi", bad.xi[..., :3])  # 3 features instead of 4
  with pytest.raises(ValueError, match="'xi'"):
    train_tok.train(config, tmp_path / "bad", splits={"train": bad})
  with pytest.raises(ValueError, match="lack 'train'"):
    train_tok.train(config, tmp_path / "bad", splits={"test": splits["test"]})
  with pytest.raises(FileNotFoundError, match="tokenizer.json"):
    load_tokenizer(tmp_path)
  broken = tmp_path / "broken.npz"
  broken.write_bytes(b"not a zip")
  with pytest.raises(ValueError, match="broken.npz"):
    tokens_lib.load_tokens(broken)


def test_parse_arg_and_presets():
  arg = common.parse_arg("tiny, q=60,quantizer=vq", tiny=False, q=0, quantizer="", lr=0.1)
  assert arg.tiny is True and arg.q == 60 and arg.quantizer == "vq" and arg.lr == 0.1
  with pytest.raises(ValueError, match="unknown key 'nope'"):
    common.parse_arg("nope=1", q=0)
  with pytest.raises(ValueError, match="q=abc"):
    common.parse_arg("q=abc", q=0)
  with pytest.raises(ValueError, match="needs a value"):
    common.parse_arg("q", q=0)
  config = tokenizer_config.get_config("q=90,quantizer=vq")
  assert config.quantizer.codebook_size == 90 and config.quantizer.kind == "vq"
  assert tokenizer_config.get_config("paper").train.learning_rate == 4.5e-6
  assert tokenizer_config.get_config(None).train.batch_size == 64
  with pytest.raises(ValueError, match="quantizer kind 'xq'"):
    TokenizerRunConfig.from_config(tokenizer_config.get_config("quantizer=xq")).model
