"""Tests of cvmdx_jax.sharding: padding, divisibility, batch placement on 1 and 2 devices."""

import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import numpy as np
import pytest

from cvmdx_jax import sharding
from cvmdx_jax.errors import UserError
from tests.subprocess_env import environ

REPO = Path(__file__).resolve().parents[2]


def test_pad_batch_pads_cyclically_and_marks_padding():
  batch = {"a": np.arange(5), "b": np.arange(10.0).reshape(5, 2)}
  padded, weight = sharding.pad_batch(batch, 4)
  np.testing.assert_array_equal(padded["a"], [0, 1, 2, 3, 4, 0, 1, 2])
  np.testing.assert_array_equal(padded["b"][5:], batch["b"][:3])
  np.testing.assert_array_equal(weight, [1, 1, 1, 1, 1, 0, 0, 0])
  assert weight.dtype == np.float32


def test_pad_batch_without_padding_and_with_fewer_rows_than_padding():
  batch = {"a": np.arange(4)}
  same, weight = sharding.pad_batch(batch, 2)
  np.testing.assert_array_equal(same["a"], batch["a"])
  np.testing.assert_array_equal(weight, np.ones(4))
  padded, weight = sharding.pad_batch(np.array([7, 9]), 5)
  np.testing.assert_array_equal(padded, [7, 9, 7, 9, 7])
  assert weight.sum() == 2


@pytest.mark.parametrize(
    "batch,multiple",
    [({"a": np.zeros(3), "b": np.zeros(2)}, 2), ({"a": np.zeros(0)}, 2), ({"a": np.zeros(3)}, 0)],
)
def test_pad_batch_rejects_bad_input(batch, multiple):
  with pytest.raises(ValueError, match="pad_batch"):
    sharding.pad_batch(batch, multiple)


def test_single_device_mesh_places_batch_and_state():
  mesh = sharding.data_mesh()
  assert mesh.axis_names == ("data",) and mesh.size == jax.device_count()
  batch = sharding.shard_batch({"x": np.ones((4, 3))}, mesh)
  assert batch["x"].sharding == sharding.batch_sharding(mesh)
  state = sharding.replicate({"w": np.zeros(2)}, mesh)
  assert state["w"].sharding.is_fully_replicated
  with pytest.raises(ValueError, match="batch_size=0"):
    sharding.check_divisible(0, mesh)


def test_two_devices_split_the_batch_and_refuse_odd_sizes():
  script = textwrap.dedent("""
      import jax, numpy as np
      from cvmdx_jax import sharding
      mesh = sharding.data_mesh()
      assert mesh.size == 2, mesh
      x = np.arange(12.0).reshape(6, 2)
      padded, w = sharding.pad_batch({"x": x[:5]}, mesh.size)
      batch = sharding.shard_batch({"x": padded["x"], "w": w}, mesh)
      shapes = sorted(s.data.shape for s in batch["x"].addressable_shards)
      assert shapes == [(3, 2), (3, 2)], shapes
      total = jax.jit(lambda b: (b["x"].sum(-1) * b["w"]).sum())(batch)
      np.testing.assert_allclose(total, x[:5].sum(), rtol=1e-6)
      try:
        sharding.shard_batch({"x": x[:5]}, mesh)
      except ValueError as e:
        assert "multiple of the number of devices (2)" in str(e), e
      else:
        raise AssertionError("odd batch accepted")
      print("OK")
  """)
  env = environ(XLA_FLAGS="--xla_force_host_platform_device_count=2", JAX_PLATFORMS="cpu")
  out = subprocess.run(
      [sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=120, cwd=REPO
  )
  assert out.returncode == 0 and out.stdout.strip() == "OK", out.stderr[-2000:]


def _fake_processes(monkeypatch, fingerprints):
  """Makes `check_same_run` see len(fingerprints) processes, this one being process 0."""
  import json

  from jax.experimental import multihost_utils

  payloads = [np.frombuffer(json.dumps(f, sort_keys=True).encode(), np.uint8) for f in fingerprints]

  def allgather(x):
    if np.ndim(x) == 0:
      return np.array([len(p) for p in payloads], np.int32)
    return np.stack([np.pad(p, (0, len(x) - len(p))) for p in payloads])

  monkeypatch.setattr(jax, "process_count", lambda: len(fingerprints))
  monkeypatch.setattr(multihost_utils, "process_allgather", allgather)


def test_same_run_in_every_process_passes(monkeypatch):
  run = {"fingerprint": {"model": {"channels": [8, 16]}}, "loop": {"seed": 0}}
  _fake_processes(monkeypatch, [run, run, run])
  sharding.check_same_run(run)


def test_another_run_in_one_process_is_refused_naming_process_and_keys(monkeypatch):
  run = {"fingerprint": {"model": {"channels": [8, 16]}}, "loop": {"seed": 0}}
  other = {"fingerprint": {"model": {"channels": [8, 32]}}, "loop": {"seed": 1, "extra": 2}}
  _fake_processes(monkeypatch, [run, run, other])
  with pytest.raises(sharding.ProcessMismatchError) as e:
    sharding.check_same_run(run, "run (workdir w)")
  assert str(e.value) == (
      "process 2 of 3 was started with another run (workdir w) than process 0; differing "
      "keys: fingerprint.model.channels: process 2 [8, 32], process 0 [8, 16]; "
      "loop.extra: process 2 2, process 0 '<absent>'; loop.seed: process 2 1, process 0 0; "
      "nothing was written"
  )


def test_use_host_devices_before_jax_starts_gives_that_many_devices():
  script = textwrap.dedent("""
      import jax
      from cvmdx_jax import sharding
      sharding.use_host_devices(2)
      assert jax.device_count() == 2 and sharding.data_mesh().size == 2
      sharding.use_host_devices(2)  # asked again: the same count passes
      print("OK")
  """)
  env = environ(JAX_PLATFORMS="cpu")
  env.pop("XLA_FLAGS", None)
  out = subprocess.run(
      [sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=120, cwd=REPO
  )
  assert out.returncode == 0 and out.stdout.strip() == "OK", out.stderr[-2000:]


def test_use_host_devices_refuses_a_late_or_contradicting_count(monkeypatch):
  have = len(jax.devices("cpu"))  # JAX has started in this process
  monkeypatch.delenv("XLA_FLAGS", raising=False)
  sharding.use_host_devices(1)
  with pytest.raises(UserError, match="JAX started with"):
    sharding.use_host_devices(have + 1)
  monkeypatch.setenv("XLA_FLAGS", f"{sharding.HOST_DEVICES_FLAG}=4")
  with pytest.raises(UserError, match="contradicts 3 host devices"):
    sharding.use_host_devices(3)
  with pytest.raises(UserError, match="expected at least 1"):
    sharding.use_host_devices(0)
