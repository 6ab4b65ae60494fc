"""Integrity of run directories (issue 15): a refused resume leaves the directory
byte-identical, corrupted files and checkpoints are refused naming the file, and a
denoiser only pairs with the exact tokeniser checkpoint it was trained on."""

import contextlib
import errno
import hashlib
import json
import os
import shutil
import warnings
from pathlib import Path

import jax
import numpy as np
import pytest

from cvmdx_jax import sharding
from cvmdx_jax.data import dataset
from cvmdx_jax.inference.bundles import load_denoiser, load_tokenizer
from cvmdx_jax.inference.predictor import IncompatibleRunsError, Predictor
from cvmdx_jax.runs import tokens
from cvmdx_jax.storage import atomic, checkpointing, checksums, locking
from cvmdx_jax.storage.checkpointing import CheckpointMismatchError
from cvmdx_jax.storage.checksums import CorruptRunError
from tests import fixtures_runs


def _diff_config(root, tokenizer_dir=None):
  return fixtures_runs.diffusion_config_for(root / "data", tokenizer_dir or root / "tokenizer")


@pytest.fixture
def runs(tiny_runs):
  """The session's tiny data, tokeniser and denoiser (tests/fixtures_runs.py); read-only."""
  return tiny_runs


@pytest.fixture(scope="module")
def other_tokenizer(tiny_runs, tmp_path_factory):
  """A second tokeniser (seed 1) of the same fingerprint and step but other weights."""
  config = fixtures_runs.tokenizer_config_for(tiny_runs / "data")
  config.seed = 1
  workdir = tmp_path_factory.mktemp("integrity") / "tokenizer_seed1"
  fixtures_runs.train_tokenizer(config, workdir)
  return workdir


def _snapshot(directory: Path) -> dict[str, tuple[bytes, int]]:
  """{relative path: (bytes, mtime_ns)} of every file except the lock (`locking`)."""
  return {
      str(p.relative_to(directory)): (p.read_bytes(), p.stat().st_mtime_ns)
      for p in sorted(directory.rglob("*"))
      if p.is_file() and not p.name.startswith(locking.LOCK_NAME)
  }


def _flip_byte(path: Path, offset: int) -> None:
  data = bytearray(path.read_bytes())
  data[offset % len(data)] ^= 0x01
  path.write_bytes(bytes(data))


def test_refused_tokenizer_resume_leaves_the_directory_unchanged(runs):
  workdir = runs / "tokenizer"
  before = _snapshot(workdir)
  assert {
      "tokenizer.json",
      "checksums.json",
      "metrics.jsonl",
      "tokens/train.npz",
      "tokens/gaussians.npz",
  } <= set(before)
  other_q = fixtures_runs.tokenizer_config_for(runs / "data", "tiny,q=5")
  other_size = fixtures_runs.tokenizer_config_for(runs / "data")
  other_size.model.encoder.latent_dim = 6
  # same fingerprint, other loop settings
  other_batch = fixtures_runs.tokenizer_config_for(runs / "data")
  other_batch.train.batch_size *= 2
  for config, differing in (
      (other_q, "codebook_size"),
      (other_size, "latent_dim"),
      (other_batch, "batch_size"),
  ):
    with pytest.raises(CheckpointMismatchError, match=differing):
      fixtures_runs.train_tokenizer(config, workdir)
    assert _snapshot(workdir) == before, differing
  splits = {s: dataset.load_split(runs / "data", s) for s in ("train", "val")}
  splits["train"] = splits["train"].take(np.arange(len(splits["train"]) - 1))  # other data
  with pytest.raises(CheckpointMismatchError, match="dataset_id"):
    fixtures_runs.train_tokenizer(
        fixtures_runs.tokenizer_config_for(runs / "data"), workdir, splits=splits
    )
  assert _snapshot(workdir) == before


def test_refused_diffusion_resume_leaves_the_directory_unchanged(runs, other_tokenizer):
  workdir = runs / "diffusion"
  before = _snapshot(workdir)
  assert {"config.json", "checksums.json", "metrics.jsonl"} <= set(before)
  other_scale = _diff_config(runs)
  other_scale.diffusion.control_scale = (4.0, 0.7 * 2)
  other_size = _diff_config(runs)
  other_size.model.base_channels *= 2
  other_tokens = _diff_config(runs, other_tokenizer)
  for config, differing in (
      (other_scale, "control_scale"),
      (other_size, "other model size"),
      (other_tokens, "params_id"),
  ):
    with pytest.raises(CheckpointMismatchError, match=differing):
      fixtures_runs.train_diffusion(config, workdir)
    assert _snapshot(workdir) == before, differing
  loaded = load_denoiser(workdir)  # still the run it was
  assert loaded.config.diffusion.control_scale == (4.0, 0.7)


def test_finished_run_rerun_with_its_config_still_verifies(runs, tmp_path):
  workdir = tmp_path / "diffusion"
  shutil.copytree(runs / "diffusion", workdir)
  before = {name: data for name, (data, _) in _snapshot(workdir).items()}
  fixtures_runs.train_diffusion(_diff_config(runs), workdir)  # nothing left to train
  assert {name: data for name, (data, _) in _snapshot(workdir).items()} == before
  with warnings.catch_warnings():
    warnings.simplefilter("error")  # every file and checkpoint carries its checksum
    Predictor.load(runs / "tokenizer", workdir)


@pytest.mark.parametrize(
    "run,name",
    [
        ("tokenizer", "tokenizer.json"),
        ("tokenizer", "tokens/gaussians.npz"),
        ("diffusion", "config.json"),
    ],
)
def test_a_flipped_byte_in_a_run_file_is_refused_naming_it(runs, tmp_path, run, name):
  for offset in (5, -40):  # in the first field and near the end of the file
    shutil.rmtree(tmp_path / run, ignore_errors=True)
    shutil.copytree(runs / run, tmp_path / run)
    _flip_byte(tmp_path / run / name, offset)
    tok_dir = tmp_path / run if run == "tokenizer" else runs / "tokenizer"
    diff_dir = tmp_path / run if run == "diffusion" else runs / "diffusion"
    with pytest.raises(CorruptRunError, match=name.split("/")[-1]):
      Predictor.load(tok_dir, diff_dir)


def test_a_flipped_byte_in_a_tokens_file_is_refused_naming_it(runs, tmp_path):
  path = tmp_path / "train.npz"
  shutil.copy(tokens.tokens_path(runs / "tokenizer", "train"), path)
  shutil.copy(runs / "tokenizer" / "tokens" / checksums.MANIFEST, tmp_path)
  tokens.load_tokens(path)  # intact copy with its manifest: verifies
  _flip_byte(path, len(path.read_bytes()) // 2)
  with pytest.raises(CorruptRunError, match="train.npz"):
    tokens.load_tokens(path)


@pytest.mark.parametrize("run", ["tokenizer", "diffusion"])
def test_a_flipped_byte_anywhere_in_a_checkpoint_is_refused_naming_the_file(runs, tmp_path, run):
  load = load_tokenizer if run == "tokenizer" else load_denoiser
  step_dir = next((runs / run / "checkpoints").iterdir())
  files = sorted(
      p.relative_to(runs / run)
      for p in step_dir.rglob("*")
      if p.is_file() and p.name != checksums.MANIFEST
  )
  assert any(f.parent.name == "d" for f in files)  # orbax's array data are among them
  for i, name in enumerate(files):
    shutil.rmtree(tmp_path / run, ignore_errors=True)
    shutil.copytree(runs / run, tmp_path / run)
    _flip_byte(tmp_path / run / name, (i + 1) * 7919)  # a different offset per file
    with pytest.raises(CheckpointMismatchError, match=f"corrupt.*{name.name}"):
      load(tmp_path / run)


def test_a_checkpoint_step_records_the_sha256_of_every_file_orbax_wrote(tmp_path):
  state = {"a": np.arange(6, dtype=np.float32), "b": {"c": np.ones((2, 3), np.int32)}}
  with checkpointing.Checkpoints(tmp_path) as ckpts:
    ckpts.save(1, state, {"run": 1})
  step = tmp_path / "1"
  manifest = json.loads((step / checksums.MANIFEST).read_text())
  # independent reference: hashlib over each file's bytes
  assert manifest == {
      p.relative_to(step).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
      for p in step.rglob("*")
      if p.is_file() and p.name != checksums.MANIFEST
  }
  assert "_CHECKPOINT_METADATA" in manifest
  rep = sharding.replicated(sharding.data_mesh())
  abstract = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=rep), state)
  restored, saved = checkpointing.load_latest(tmp_path, abstract)
  assert saved == {"run": 1} and np.array_equal(restored["b"]["c"], state["b"]["c"])
  (step / "extra").write_text("x")  # an added file is refused too
  with pytest.raises(CheckpointMismatchError, match="corrupt.*'extra'"):
    checkpointing.load_latest(tmp_path, abstract)
  (step / "extra").unlink()
  (step / checksums.MANIFEST).unlink()  # no manifest: refused, not trusted
  with pytest.raises(CheckpointMismatchError, match="no checksums.json"):
    checkpointing.load_latest(tmp_path, abstract)


def test_denoiser_refuses_a_tokeniser_of_same_fingerprint_and_step_but_other_weights(
    runs, other_tokenizer
):
  a = load_tokenizer(runs / "tokenizer")
  b = load_tokenizer(other_tokenizer)
  assert a.fingerprint == b.fingerprint and a.checkpoint.step == b.checkpoint.step
  with pytest.raises(IncompatibleRunsError, match="params_id"):
    Predictor.load(other_tokenizer, runs / "diffusion")


def test_denoiser_refuses_its_tokeniser_trained_further(runs, tmp_path):
  shutil.copytree(runs / "tokenizer", tmp_path / "tokenizer")
  config = fixtures_runs.tokenizer_config_for(runs / "data")
  config.train.num_epochs += 1
  fixtures_runs.train_tokenizer(config, tmp_path / "tokenizer")
  with pytest.raises(IncompatibleRunsError, match="step"):
    Predictor.load(tmp_path / "tokenizer", runs / "diffusion")


def test_run_files_without_checksums_are_refused(runs, tmp_path):
  shutil.copytree(runs / "tokenizer", tmp_path / "tokenizer")
  (tmp_path / "tokenizer" / checksums.MANIFEST).unlink()
  with pytest.raises(CorruptRunError, match="tokenizer.json: no checksum"):
    Predictor.load(tmp_path / "tokenizer", runs / "diffusion")


def test_checksummed_writes_leave_a_verifiable_manifest(tmp_path):
  path = tmp_path / "x.json"
  checksums.write_json(path, {"a": 1})
  checksums.write_json(path, {"a": 2})
  manifest = json.loads((tmp_path / checksums.MANIFEST).read_text())
  assert manifest == {"x.json": hashlib.sha256(path.read_bytes()).hexdigest()}
  assert checksums.read_json(path) == {"a": 2}
  path.write_text('{"a": 3}\n')
  with pytest.raises(CorruptRunError, match="x.json"):
    checksums.read_json(path)


def test_a_failed_group_write_leaves_files_and_manifest_as_they_were(tmp_path, monkeypatch):
  checksums.write_json(tmp_path / "metrics.json", {"a": 1})
  (tmp_path / "old.png").write_bytes(b"old")
  before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
  real = atomic.writing

  @contextlib.contextmanager
  def full_at_png(path, mode="wb"):
    with real(path, mode) as f:
      if Path(path).suffix == ".png":
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
      yield f

  monkeypatch.setattr(atomic, "writing", full_at_png)
  files = {tmp_path / "metrics.json": b'{"a": 2}\n', tmp_path / "old.png": b"new"}
  for directory in (tmp_path, tmp_path / "fresh"):
    directory.mkdir(exist_ok=True)
    with pytest.raises(OSError, match="No space left"):
      checksums.write_all({directory / p.name: data for p, data in files.items()})
  assert {p.name: p.read_bytes() for p in tmp_path.iterdir() if p.is_file()} == before
  assert list((tmp_path / "fresh").iterdir()) == []
  monkeypatch.setattr(atomic, "writing", real)
  checksums.write_all(files)
  assert checksums.read_json(tmp_path / "metrics.json") == {"a": 2}
  assert checksums.read_bytes(tmp_path / "old.png") == b"new"
