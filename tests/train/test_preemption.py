"""Stopping on SIGTERM / SIGINT at a step boundary (cvmdx_jax.train.preemption, train.loop):
one process, in-process; the multi-process cases are in test_distributed.py."""

import json
import os
import signal

import jax
import numpy as np
import pytest

from cvmdx_jax.storage import checkpointing
from cvmdx_jax.train import preemption
from tests.train import toy

M, BATCH, EPOCHS = 36, 8, 3  # 5 steps per epoch, 15 in all


def _task(armed: dict):
  """The toy task whose step sends `armed["signal"]` to this process from inside global
  step `armed["at"]` (a host callback; async dispatch may run one more step first)."""
  init_fn, step_fn = toy.make_task()

  def fire(step):
    if armed.get("at") == int(step):
      os.kill(os.getpid(), armed["signal"])

  def signalling_step(state, batch, key):
    jax.debug.callback(fire, state["step"])
    return step_fn(state, batch, key)

  return init_fn, signalling_step


def _train(workdir, armed):
  init_fn, step_fn = _task(armed)
  return toy.train(
      workdir=workdir,
      init_fn=init_fn,
      step_fn=step_fn,
      data=toy.make_data(M),
      batch_size=BATCH,
      num_epochs=EPOCHS,
      seed=3,
      fingerprint={"t": "p"},
  )


def _losses(workdir):
  lines = (workdir / "metrics.jsonl").read_text().splitlines()
  return [(r["epoch"], r["loss"], r["grad_norm"]) for r in map(json.loads, lines)]


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
  workdir = tmp_path_factory.mktemp("reference")
  return toy.flat_params(_train(workdir, {})), _losses(workdir)


@pytest.mark.parametrize(
    "number, status",
    [(signal.SIGTERM, 143), pytest.param(signal.SIGINT, 130, marks=pytest.mark.slow)],
)
def test_signal_mid_epoch_saves_the_next_step_and_resumes_bit_identical(
    tmp_path, reference, number, status
):
  with pytest.raises(preemption.Stopped) as stop:
    _train(tmp_path, {"at": 7, "signal": number})
  assert stop.value.code == status and "saved global step" in stop.value.message
  saved = [int(p.name) for p in (tmp_path / "preempted").iterdir()]
  assert len(saved) == 1 and 8 <= saved[0] <= 9, saved  # epoch 2, before its end
  assert sorted(p.name for p in (tmp_path / "checkpoints").iterdir()) == ["1"]
  assert [r[0] for r in _losses(tmp_path)] == [1]
  assert signal.getsignal(number) is not None  # handlers restored (not ours)
  params, losses = reference
  np.testing.assert_array_equal(toy.flat_params(_train(tmp_path, {})), params)
  assert _losses(tmp_path) == losses  # epoch 2's mean spans both runs
  assert not (tmp_path / "preempted").exists()  # dropped once epoch 2 was saved


def test_sigint_during_a_checkpoint_save_stops_after_it(tmp_path, reference, monkeypatch):
  save = checkpointing.Checkpoints.save

  def interrupted_save(self, step, state, metadata):
    os.kill(os.getpid(), signal.SIGINT)  # handled inside save (the main thread is there)
    save(self, step, state, metadata)

  monkeypatch.setattr(checkpointing.Checkpoints, "save", interrupted_save)
  with pytest.raises(preemption.Stopped) as stop:
    _train(tmp_path, {})
  assert stop.value.code == 130 and "the last checkpoint holds global step 5" in stop.value.message
  assert sorted(p.name for p in (tmp_path / "checkpoints").iterdir()) == ["1"]
  assert not (tmp_path / "preempted").exists()
  monkeypatch.setattr(checkpointing.Checkpoints, "save", save)
  np.testing.assert_array_equal(toy.flat_params(_train(tmp_path, {})), reference[0])
