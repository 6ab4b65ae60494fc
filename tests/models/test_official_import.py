"""Official checkpoints: the torch-free .pt reader and the state dict -> U-Net import,
against a numpy forward pass of the official model written from its structure."""

import os
import pickle
import subprocess
import sys
import warnings
import zipfile
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cvmdx_jax.inference.bundles import load_denoiser
from cvmdx_jax.models import official_import, torch_zip, unet1d
from cvmdx_jax.models.official_state import OfficialCheckpointError, unet_config, unwrap_state_dict
from cvmdx_jax.storage import locking
from tests.models import official_fixture as fx
from tests.subprocess_env import pythonpath

REPO = Path(__file__).resolve().parents[2]
Q = 7


@pytest.fixture(scope="module")
def official():
  return fx.state_dict(np.random.default_rng(0), Q)


def test_reader_rebuilds_tensors_and_containers(tmp_path, monkeypatch):
  base = np.arange(12, dtype=np.float32)
  obj = {
      "dense": np.arange(6, dtype=np.float32).reshape(2, 3),
      "ints": np.array([3, -1, 2**40], np.int64),
      # a strided view: storage 0..11, offset 1, size (2, 3), stride (1, 4)
      "view": fx._Tensor("v", base, offset=1, size=(2, 3), stride=(1, 4)),
      "meta": {"step": 5, "names": ["a", "b"]},
  }
  path = tmp_path / "x.pt"
  fx.write_pt(path, obj, monkeypatch, name="x")
  got = torch_zip.read_pt(path)
  np.testing.assert_array_equal(got["dense"], obj["dense"])
  assert got["ints"].dtype == np.int64 and got["ints"].tolist() == [3, -1, 2**40]
  np.testing.assert_array_equal(got["view"], [[1, 5, 9], [2, 6, 10]])
  assert got["meta"] == {"step": 5, "names": ["a", "b"]}


def test_reader_refuses_code_and_other_formats(tmp_path):
  class Evil:  # a pickle that would call os.getpid() when loaded

    def __reduce__(self):
      return (os.getpid, ())

  path = tmp_path / "evil.pt"
  with zipfile.ZipFile(path, "w") as z:
    z.writestr("evil/data.pkl", pickle.dumps({"a": Evil()}, protocol=2))
  with pytest.raises(torch_zip.TorchFileError, match="getpid"):
    torch_zip.read_pt(path)
  legacy = tmp_path / "legacy.pt"
  legacy.write_bytes(pickle.dumps({"a": 1}))
  with pytest.raises(torch_zip.TorchFileError, match="not a PyTorch zip"):
    torch_zip.read_pt(legacy)


def test_config_is_read_from_the_state_dict(official):
  cfg = unet_config(official)
  assert (
      cfg.num_tokens,
      cfg.null_token,
      cfg.base_channels,
      cfg.channel_mult,
      cfg.num_res_blocks,
      cfg.emb_mult,
      cfg.attention_levels,
      cfg.num_heads,
      cfg.groups,
  ) == (Q, Q, 32, (1, 2), 1, 2, (1,), 4, 32)


def test_imported_unet_equals_the_official_forward(official, tmp_path, monkeypatch):
  path = tmp_path / "ema_0.9999_000100.pt"
  fx.write_pt(path, official, monkeypatch)
  cfg, params = official_import.load_official(path)
  graphdef = unet1d.make_graphdef(cfg)
  rng = np.random.default_rng(1)
  x = rng.normal(size=(8, 2, 125)).astype(np.float32)
  t = np.repeat([0, 37, 500, 999], 2)
  y = np.array([Q, 3] * 4)  # null label and a real one at each t
  want = fx.forward(official, x, t, y)
  got = unet1d.apply_unet(
      graphdef, params, jnp.asarray(x.transpose(0, 2, 1)), jnp.asarray(t), jnp.asarray(y)
  )
  assert np.abs(want).max() > 0.3
  np.testing.assert_allclose(np.asarray(got).transpose(0, 2, 1), want, atol=1e-4)
  # the check can fail: the same weights padded on the right only give other outputs
  right_only = fx.forward(official, x, t, y, left=0)
  assert np.abs(right_only - want).max() > 1e-2


def test_wrapped_and_prefixed_state_dicts(official, monkeypatch):
  other = {k: v + 1 for k, v in official.items()}
  wrapped = {"model": official, "ema": {f"module.{k}": v for k, v in other.items()}, "step": 3}
  with pytest.raises(OfficialCheckpointError, match="key="):
    unwrap_state_dict(wrapped, "ckpt.pt")
  got = unwrap_state_dict(wrapped, "ckpt.pt", key="ema")
  np.testing.assert_array_equal(got["out.2.bias"], other["out.2.bias"])
  single = unwrap_state_dict({"state_dict": official, "epoch": 1}, "c.pt")
  np.testing.assert_array_equal(single["label_emb.weight"], official["label_emb.weight"])


def test_mismatched_state_dicts_are_refused(official):
  extra = {**official, "input_blocks.1.0.foo.weight": np.zeros(3, np.float32)}
  with pytest.raises(OfficialCheckpointError, match="foo"):
    official_import.params_from_state_dict(extra, unet_config(official))
  wrong = dict(official)
  wrong["out.2.weight"] = np.zeros((4, 32, 3), np.float32)  # learn_sigma=True
  with pytest.raises(OfficialCheckpointError, match="2 -> 4"):
    unet_config(wrong)


def test_import_script_writes_a_loadable_run(official, tmp_path, monkeypatch):
  path = tmp_path / "model000100.pt"
  fx.write_pt(path, official, monkeypatch)
  workdir = tmp_path / "run"
  # an import killed -9: a checkpoint step and no config.json (the new one would collide)
  (workdir / "checkpoints" / "1").mkdir(parents=True)
  cmd = [
      sys.executable,
      "experiments/import_official.py",
      f"--checkpoint={path}",
      f"--workdir={workdir}",
  ]
  env = {"PYTHONPATH": pythonpath(), "PATH": "/usr/bin:/bin", "JAX_PLATFORMS": "cpu"}
  done = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True)
  assert done.returncode == 0, done.stderr
  with warnings.catch_warnings():
    warnings.simplefilter("error")
    denoiser = load_denoiser(workdir)
  assert denoiser.unet == unet_config(official)
  assert denoiser.config.sampling.mode == "official"
  _, want = official_import.load_official(path)
  jax.tree.map(np.testing.assert_array_equal, denoiser.params, want)
  again = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True)
  assert again.returncode == 2 and "exists" in again.stderr


def _import(args, workdir, timeout=300):
  cmd = [sys.executable, "experiments/import_official.py", *args, f"--workdir={workdir}"]
  env = {"PYTHONPATH": pythonpath(), "PATH": "/usr/bin:/bin", "JAX_PLATFORMS": "cpu"}
  return subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=timeout)


def _one_line_error(done, *parts):
  lines = done.stderr.strip().splitlines()
  assert done.returncode == 2 and len(lines) == 1, done.stderr
  assert lines[0].startswith("import_official: error: ") and "Traceback" not in done.stderr
  assert all(p in lines[0] for p in parts), lines[0]


@pytest.mark.parametrize(
    "name, value, message",
    [
        ("input_blocks.0.0.weight", np.zeros((0, 2, 3), np.float32), "has shape (0, 2, 3)"),
        ("label_emb.weight", np.array(1.0, np.float32), "has shape ()"),
        ("time_embed.0.weight", np.zeros(64, np.float32), "has shape (64,)"),
        (
            "input_blocks.1.0.in_layers.2.weight",
            np.zeros((32, 96), np.float32),
            "has shape (32, 96); its layer needs 3 dimensions",
        ),
        (
            "input_blocks.1.0.out_layers.3.weight",
            np.zeros((32, 32, 5), np.float32),
            "has shape (32, 32, 5); the architecture read from the file expects (32, 32, 3)",
        ),
        (
            "middle_block.1.qkv.weight",
            np.zeros((190, 64, 1), np.float32),
            "has shape (190, 64, 1); an attention block of 64 channels has (192, 64, 1)",
        ),
        ("out.0.bias", np.full(32, np.nan, np.float32), "out.0.bias holds NaN or Inf"),
        ("label_emb.weight", np.full((8, 64), np.inf, np.float32), "label_emb.weight holds NaN"),
    ],
)
def test_malformed_parameters_name_file_and_parameter(
    official, tmp_path, monkeypatch, name, value, message
):
  path = tmp_path / "bad.pt"
  fx.write_pt(path, {**official, name: value}, monkeypatch)
  with pytest.raises(OfficialCheckpointError) as e:
    official_import.load_official(path)
  assert str(e.value).startswith(f"{path}: ") and name in str(e.value)
  assert message in str(e.value) and "\n" not in str(e.value)


def test_non_string_keys_are_refused(official, tmp_path, monkeypatch):
  path = tmp_path / "int_keys.pt"
  fx.write_pt(path, {**official, 3: np.zeros(2, np.float32)}, monkeypatch)
  with pytest.raises(
      OfficialCheckpointError, match="int_keys.pt: the state dict has a key 3 of type int"
  ):
    official_import.load_official(path)
  fx.write_pt(path, {0: np.zeros(2, np.float32)}, monkeypatch)  # no parameter names at all
  with pytest.raises(OfficialCheckpointError, match="found entries"):
    official_import.load_official(path)


def test_import_script_refuses_with_one_line(official, tmp_path, monkeypatch):
  flat = tmp_path / "flat.pt"
  fx.write_pt(
      flat, {**official, "input_blocks.0.0.weight": np.zeros((32, 6), np.float32)}, monkeypatch
  )
  _one_line_error(
      _import([f"--checkpoint={flat}"], tmp_path / "a"),
      str(flat),
      "input_blocks.0.0.weight",
      "(32, 6)",
  )
  good = tmp_path / "good.pt"
  fx.write_pt(good, official, monkeypatch)
  _one_line_error(
      _import([f"--checkpoint={good}", "--num_heads=3"], tmp_path / "b"),
      "--num_heads=3",
      "[64] channels",
      "divisible by 3 heads",
  )
  assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_a_held_workdir_is_refused_with_the_lock_message(official, tmp_path, monkeypatch):
  good = tmp_path / "good.pt"
  fx.write_pt(good, official, monkeypatch)
  workdir = tmp_path / "run"
  with locking.hold(workdir):  # another import (this process) is writing it
    done = _import([f"--checkpoint={good}"], workdir)
    assert os.listdir(workdir) == [locking.LOCK_NAME]
  _one_line_error(done, f"workdir {workdir} is in use by pid {os.getpid()}")
  assert not workdir.exists()
