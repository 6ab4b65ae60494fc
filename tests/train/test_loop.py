"""Tests of the shared training loop (cvmdx_jax.train.loop) on a toy regression task."""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cvmdx_jax.storage.checkpointing import CheckpointMismatchError
from cvmdx_jax.train import loop
from tests.subprocess_env import environ
from tests.train import toy

REPO = Path(__file__).resolve().parents[2]
JOB = REPO / "tests" / "train" / "toy_job.py"


def _train(workdir, epochs, seed=0, m=20, batch_size=4, **kw):
  init_fn, step_fn = toy.make_task(**{k: kw.pop(k) for k in ("hidden", "nan_at") if k in kw})
  return toy.train(
      workdir=workdir,
      init_fn=init_fn,
      step_fn=step_fn,
      data=toy.make_data(m),
      batch_size=batch_size,
      num_epochs=epochs,
      seed=seed,
      fingerprint=kw.pop("fingerprint", {"q": 60, "dataset": "toy"}),
      **kw,
  )


def _epochs_logged(workdir):
  lines = (Path(workdir) / "metrics.jsonl").read_text().splitlines()
  return [json.loads(line)["epoch"] for line in lines]


def _job(workdir, devices=1, **args):
  env = environ(XLA_FLAGS=f"--xla_force_host_platform_device_count={devices}", JAX_PLATFORMS="cpu")
  cmd = [sys.executable, str(JOB), f"--workdir={workdir}"] + [f"--{k}={v}" for k, v in args.items()]
  return cmd, env


def _run_job(workdir, devices=1, **args):
  cmd, env = _job(workdir, devices, **args)
  out = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
  result = json.loads(out.stdout.splitlines()[-1]) if out.returncode == 0 else None
  return out, result


def test_padded_last_batch_matches_hand_computed_sgd(tmp_path):
  rng = np.random.default_rng(3)
  x, y = rng.normal(size=(5, 2)), rng.normal(size=5)
  lr, seed, w0 = 0.1, 11, np.array([0.5, -0.25])

  def step_fn(state, batch, key):
    err = batch["x"] @ state["w"] - batch["y"]
    loss_fn = lambda w: jnp.sum(batch["weight"] * (batch["x"] @ w - batch["y"]) ** 2) / jnp.sum(
        batch["weight"]
    )
    loss, grad = jax.value_and_grad(loss_fn)(state["w"])
    return {"w": state["w"] - lr * grad}, {"loss": loss, "max_err": jnp.max(jnp.abs(err))}

  state = toy.train(
      workdir=tmp_path,
      init_fn=lambda key: {"w": jnp.asarray(w0, jnp.float32)},
      step_fn=step_fn,
      data={"x": x.astype(np.float32), "y": y.astype(np.float32)},
      batch_size=4,
      num_epochs=2,
      seed=seed,
      fingerprint={},
  )
  w, losses = w0.copy(), []
  for epoch in range(2):  # the documented order; the last batch holds one real row
    order = np.random.default_rng([seed, epoch]).permutation(5)
    sq = []
    for rows in (order[:4], order[4:]):
      r = x[rows] @ w - y[rows]
      sq.append(np.mean(r**2) * len(rows))
      w = w - lr * 2 * x[rows].T @ r / len(rows)
    losses.append(sum(sq) / 5)  # epoch loss: mean over the 5 real examples
  np.testing.assert_allclose(np.asarray(state["w"]), w, rtol=1e-5)
  logged = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
  np.testing.assert_allclose([r["loss"] for r in logged], losses, rtol=1e-5)
  assert [r["step"] for r in logged] == [2, 4]


def test_two_devices_match_one_device_and_odd_batch_is_refused(tmp_path):
  one, r1 = _run_job(tmp_path / "one", devices=1, epochs=3)
  two, r2 = _run_job(tmp_path / "two", devices=2, epochs=3)
  assert r1 and r2, one.stderr[-2000:] + two.stderr[-2000:]
  assert (r1["devices"], r2["devices"]) == (1, 2)
  np.testing.assert_allclose(r2["params"], r1["params"], rtol=1e-5, atol=1e-6)
  np.testing.assert_allclose(r2["loss"], r1["loss"], rtol=1e-5)
  odd, _ = _run_job(tmp_path / "odd", devices=2, epochs=1, batch_size=5)
  assert odd.returncode == 2
  assert "batch_size=5 must be a positive multiple of the number of devices (2)" in odd.stderr


@pytest.mark.slow
@pytest.mark.parametrize("task", ["diffusion", "tokenizer"])
def test_real_models_on_two_devices_match_one_device(tmp_path, task):
  args = dict(task=task, epochs=1, m=12, batch_size=4)
  one, r1 = _run_job(tmp_path / "one", devices=1, **args)
  two, r2 = _run_job(tmp_path / "two", devices=2, **args)
  assert r1 and r2, one.stderr[-2000:] + two.stderr[-2000:]
  assert (r1["devices"], r2["devices"]) == (1, 2)
  np.testing.assert_allclose(r2["loss"], r1["loss"], rtol=1e-4)
  np.testing.assert_allclose(r2["params"], r1["params"], rtol=1e-4, atol=1e-5)


def test_resumed_run_is_bit_identical_and_finished_run_does_not_train(tmp_path):
  full = _train(tmp_path / "full", epochs=4)
  _train(tmp_path / "cut", epochs=2)
  resumed = _train(tmp_path / "cut", epochs=4)
  np.testing.assert_array_equal(toy.flat_params(resumed), toy.flat_params(full))
  assert int(resumed["step"]) == 4 * 5
  assert _epochs_logged(tmp_path / "cut") == [1, 2, 3, 4]
  assert sorted(p.name for p in (tmp_path / "cut" / "checkpoints").iterdir()) == ["3", "4"]

  def refuse(*_):
    raise AssertionError("a finished run must not step")

  again = toy.train(
      workdir=tmp_path / "full",
      init_fn=toy.make_task()[0],
      step_fn=refuse,
      data=toy.make_data(20),
      batch_size=4,
      num_epochs=4,
      seed=0,
      fingerprint={"q": 60, "dataset": "toy"},
  )
  np.testing.assert_array_equal(toy.flat_params(again), toy.flat_params(full))


def test_same_seed_identical_other_seed_different(tmp_path):
  a = toy.flat_params(_train(tmp_path / "a", epochs=2, seed=5))
  b = toy.flat_params(_train(tmp_path / "b", epochs=2, seed=5))
  c = toy.flat_params(_train(tmp_path / "c", epochs=2, seed=6))
  np.testing.assert_array_equal(a, b)
  assert np.abs(a - c).max() > 1e-3


def test_non_finite_loss_stops_with_step_and_keeps_last_good_checkpoint(tmp_path):
  with pytest.raises(loop.TrainingError, match=r"non-finite loss=nan at global step 7 \(epoch 2\)"):
    _train(tmp_path, epochs=3, nan_at=7)  # 5 steps per epoch: step 7 is in epoch 2
  assert [p.name for p in (tmp_path / "checkpoints").iterdir()] == ["1"]
  assert _epochs_logged(tmp_path) == [1]
  state, fingerprint = toy.restore(tmp_path, toy.make_task()[0])
  assert int(state["step"]) == 5 and fingerprint == {"q": 60, "dataset": "toy"}
  assert np.isfinite(toy.flat_params(state)).all()


def test_other_fingerprint_or_model_size_or_no_checkpoint_is_refused(tmp_path):
  _train(tmp_path, epochs=1)
  with pytest.raises(CheckpointMismatchError, match="q: saved 60, expected 90"):
    _train(tmp_path, epochs=2, fingerprint={"q": 60 + 30, "dataset": "toy"})
  with pytest.raises(CheckpointMismatchError, match="dataset: saved 'toy', expected 'highd'"):
    toy.restore(tmp_path, toy.make_task()[0], {"q": 60, "dataset": "highd"})
  with pytest.raises(CheckpointMismatchError, match="loop.batch_size: saved 4, expected 2"):
    _train(tmp_path, epochs=2, batch_size=2)
  with pytest.raises(CheckpointMismatchError, match=r"params/l1/kernel.*\(3, 8\).*\(3, 16\)"):
    toy.restore(tmp_path, toy.make_task(hidden=16)[0])
  with pytest.raises(CheckpointMismatchError, match="no complete checkpoint"):
    toy.restore(tmp_path / "empty", toy.make_task()[0])
  assert not (tmp_path / "empty").exists()


def test_corrupt_checkpoint_is_named(tmp_path):
  _train(tmp_path, epochs=1)
  meta = tmp_path / "checkpoints" / "1" / "state" / "_METADATA"
  meta.write_text(meta.read_text()[:40])  # truncated
  with pytest.raises(CheckpointMismatchError, match=f"{tmp_path / 'checkpoints' / '1'} is corrupt"):
    toy.restore(tmp_path, toy.make_task()[0])
  with pytest.raises(CheckpointMismatchError, match="is corrupt"):
    _train(tmp_path, epochs=2)


def test_half_written_checkpoints_are_never_picked_up(tmp_path):
  _train(tmp_path, epochs=2)
  ckpts = tmp_path / "checkpoints"
  shutil.copytree(ckpts / "2", ckpts / "3")
  (ckpts / "3" / "commit_success.txt").unlink()  # finished writing, never committed
  shutil.copytree(ckpts / "2", ckpts / "4.orbax-checkpoint-tmp-1234")  # killed mid-write
  state, _ = toy.restore(tmp_path, toy.make_task()[0])
  assert int(state["step"]) == 2 * 5
  resumed = _train(tmp_path, epochs=3)
  np.testing.assert_array_equal(
      toy.flat_params(resumed), toy.flat_params(_train(tmp_path / "ref", epochs=3))
  )
  assert sorted(p.name for p in ckpts.iterdir()) == ["2", "3"]


def test_bad_arguments_are_refused(tmp_path):
  init_fn, step_fn = toy.make_task()
  kw = dict(
      workdir=tmp_path, init_fn=init_fn, step_fn=step_fn, num_epochs=1, seed=0, fingerprint={}
  )
  with pytest.raises(ValueError, match="common leading dimension"):
    toy.train(data={"x": np.zeros((4, 3)), "y": np.zeros((5, 1))}, batch_size=2, **kw)
  with pytest.raises(ValueError, match="'weight'"):
    toy.train(data={"x": np.zeros((4, 3)), "weight": np.zeros(4)}, batch_size=2, **kw)
  with pytest.raises(ValueError, match="batch_size=0"):
    toy.train(data=toy.make_data(4), batch_size=0, **kw)
  with pytest.raises(ValueError, match="PRNG key"):
    toy.train(
        data=toy.make_data(4),
        batch_size=2,
        **{**kw, "init_fn": lambda key: {"key": key, **init_fn(key)}},
    )
  with pytest.raises(ValueError, match="fingerprint must be JSON"):
    toy.train(data=toy.make_data(4), batch_size=2, **{**kw, "fingerprint": {"f": object}})
  with pytest.raises(ValueError, match="is not held"):  # the caller holds the workdir
    loop.train(data=toy.make_data(4), batch_size=2, **kw)
  assert not list(tmp_path.iterdir())


@pytest.mark.slow
def test_sigkill_at_random_moments_then_rerun_ends_bit_identical(tmp_path):
  args = dict(epochs=10, m=64, batch_size=8, sleep=0.2)
  _, reference = _run_job(tmp_path / "ref", **args)
  assert reference
  rng = np.random.default_rng()
  for attempt in range(2):
    cmd, env = _job(tmp_path / "killed", **args)
    proc = subprocess.Popen(
        cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True
    )
    assert proc.stdout.readline().startswith("epoch"), "the job did not start training"
    delay = rng.uniform(0.0, 0.6)
    try:
      proc.wait(timeout=delay)
    except subprocess.TimeoutExpired:
      proc.kill()  # SIGKILL
      proc.wait()
    proc.stdout.close()
    assert proc.returncode == -9, f"attempt {attempt}: job ended before the kill ({delay=})"
  out, resumed = _run_job(tmp_path / "killed", **args)
  assert resumed, out.stderr[-2000:]
  np.testing.assert_array_equal(resumed["params"], reference["params"])
  assert _epochs_logged(tmp_path / "killed") == list(range(1, 11))
