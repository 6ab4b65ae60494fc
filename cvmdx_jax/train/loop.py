"""The shared data-parallel, resumable training loop of the tokeniser and the diffusion model.

`train` runs `step_fn` over shuffled, padded global batches on a "data" mesh of all
visible devices (state replicated, batches split), writes one JSON line of metrics per
epoch to `<workdir>/metrics.jsonl` and an orbax checkpoint to `<workdir>/checkpoints`.
Everything a step sees is a function of (seed, epoch, global step): epoch e uses the
example order `np.random.default_rng([seed, e]).permutation(M)` and global step g the key
`jax.random.fold_in(jax.random.key(seed), g)`, so a run that is killed and rerun with the
same command ends bit-identical to one that never stopped.

Epochs are counted from 1 in the metrics lines, in `epoch_end_fn` and as checkpoint
steps: checkpoint `k` holds the state after k complete epochs.

The caller holds the workdir (`storage.locking.hold`, taken once by the trainers around
everything they write), so a second run on it is refused; `train` checks that it is held.
Under `jax.distributed` (see `sharding.initialize_distributed`) every process runs `train`
with the same arguments and data: the mesh spans all processes' devices, each process feeds
the rows of every global batch that its devices hold, orbax writes one checkpoint together,
and only process 0 writes `metrics.jsonl`; the result matches a single-process run.
"""

import os
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import jax
import numpy as np

from cvmdx_jax import sharding
from cvmdx_jax.runs import layout
from cvmdx_jax.storage import checkpointing, identity, locking
from cvmdx_jax.train import preemption
from cvmdx_jax.train.epochs import (
    EpochRunner,
    State,
    StepFn,
    TrainingError,
    init_key,
    steps_per_epoch,
)

__all__ = [
    "State",
    "StepFn",
    "TrainingError",
    "init_key",
    "run_settings",
    "steps_per_epoch",
    "train",
]


def _traced_init(init_fn: Callable[[jax.Array], State], mesh, seed: int):
  """`init_fn` traced once for `seed`'s key, its state replicated on `mesh`: `.out_info` is
  the state's shapes and dtypes (to restore a checkpoint into), `.lower()` compiles it (a
  fresh run); refuses typed PRNG keys in the state."""
  traced = jax.jit(init_fn, out_shardings=sharding.replicated(mesh)).trace(init_key(seed))
  for path, leaf in jax.tree_util.tree_flatten_with_path(traced.out_info)[0]:
    if jax.dtypes.issubdtype(leaf.dtype, jax.dtypes.prng_key):
      raise ValueError(
          f"init_fn state leaf {jax.tree_util.keystr(path)} is a PRNG key; keep "
          "keys out of the train state (train derives them from seed and step)"
      )
  return traced


def _check_data(data: Mapping[str, Any], batch_size: int) -> int:
  if not data:
    raise ValueError("train: data is empty")
  if "weight" in data:
    raise ValueError("train: data must not contain 'weight' (the loop adds it)")
  sizes = {k: np.shape(v)[0] if np.ndim(v) else None for k, v in data.items()}
  if len(set(sizes.values())) != 1 or None in sizes.values():
    raise ValueError(f"train: data arrays need one common leading dimension, got {sizes}")
  m = next(iter(sizes.values()))
  if m == 0:
    raise ValueError("train: data has no examples")
  if not isinstance(batch_size, int) or batch_size <= 0:
    raise ValueError(f"train: batch_size={batch_size!r} must be a positive int")
  return m


def _check_arguments(workdir, data, batch_size: int, checkpoint_every: int, keep: int) -> int:
  """M, the number of examples, once `train`'s arguments are checked (ValueError)."""
  if not locking.is_held(workdir):
    raise ValueError(
        f"train: workdir {workdir} is not held; call train inside " "storage.locking.hold(workdir)"
    )
  m = _check_data(data, batch_size)
  if checkpoint_every < 1 or keep < 1:
    raise ValueError(f"train: checkpoint_every={checkpoint_every} and keep={keep} must be >= 1")
  return m


def _run_meta(workdir, data, m: int, batch_size: int, seed: int, fingerprint, schedule) -> dict:
  """The run's identity stored with each checkpoint; under `jax.distributed` checked against
  process 0's (with the data's content id, the workdir and the `schedule` (num_epochs,
  checkpoint_every, keep))."""
  run_meta = {
      "fingerprint": identity.to_json(fingerprint),
      "loop": {"seed": seed, "batch_size": batch_size, "num_examples": m},
  }
  if jax.process_count() > 1:  # every process must run the same job on the same data
    sharding.check_same_run(
        {
            **run_meta,
            "data": identity.content_id(data),
            "workdir": str(Path(workdir).resolve()),
            "schedule": list(schedule),
        },
        f"run (workdir {workdir})",
    )
  return run_meta


def run_settings(config) -> dict:
  """The keyword arguments of `train` that a run config fixes: batch_size, num_epochs,
  checkpoint_every and keep of its `train` section, and its `seed`."""
  section = config.train
  return {
      "batch_size": section.batch_size,
      "num_epochs": section.num_epochs,
      "seed": config.seed,
      "checkpoint_every": section.checkpoint_every,
      "keep": section.keep,
  }


def train(
    *,
    workdir: str | os.PathLike,
    init_fn: Callable[[jax.Array], State],
    step_fn: StepFn,
    data: Mapping[str, np.ndarray],
    batch_size: int,
    num_epochs: int,
    seed: int,
    fingerprint: Any,
    checkpoint_every: int = 1,
    keep: int = 2,
    epoch_end_fn: Callable[[State, int], dict[str, Any]] | None = None,
    on_start: Callable[[], None] | None = None,
    desc: str = "train",
) -> State:
  """Trains (or resumes, or returns a finished run's final state) data-parallel.

  Args:
    workdir: run directory; holds `checkpoints/` and `metrics.jsonl`; the caller holds
      its lock (`storage.locking.hold`).
    init_fn: `init_fn(key) -> state`, a pytree of arrays (no PRNG keys).
    step_fn: pure `step_fn(state, batch, key) -> (state, metrics)`; `batch` holds the
      arrays of `data` for `batch_size` examples plus `weight` (batch_size,) float32 (0 on
      padding rows); `metrics` is a dict of scalars with "loss" (and maybe "grad_norm").
    data: dict of numpy arrays with a common leading dimension M (the training set).
    batch_size: global batch size; must be a multiple of the device count.
    num_epochs: total epochs of the run (a rerun with more epochs continues it).
    seed: fixes the initial state, the example order and every step key.
    fingerprint: JSON-able identity of the run (model config, dataset id, ...) stored with
      each checkpoint; resuming with another raises CheckpointMismatchError.
    checkpoint_every: save after every this many epochs (and after the last).
    keep: number of latest checkpoints kept.
    epoch_end_fn: `epoch_end_fn(state, epoch) -> dict` of extra JSON-able values logged
      (`state` as `train` returns it).
    on_start: called once the workdir's checkpoint (if any) has been checked, before
      `train` writes anything into the workdir (e.g. to write the run's own files).
    desc: progress bar label.

  Returns:
    The state after `num_epochs` epochs, replicated on the mesh (with several processes:
    `sharding.local_copy` of it, so that single-process code can go on with it).

  Raises:
    ValueError: bad arguments (e.g. batch_size not divisible by the device count, or
      the workdir not held).
    sharding.ProcessMismatchError: (in every process, before anything is written) a
      process's fingerprint, workdir, loop settings, schedule or data differ from
      process 0's.
    CheckpointMismatchError: the workdir's checkpoint belongs to another run or is broken.
    TrainingError: a non-finite loss or grad_norm (names the global step and epoch).
    preemption.Stopped: SIGTERM or SIGINT arrived; the state at the next step boundary
      is saved (module docstring); exits with status 143 or 130.
  """
  m = _check_arguments(workdir, data, batch_size, checkpoint_every, keep)
  mesh = sharding.data_mesh()
  sharding.check_divisible(batch_size, mesh)
  init = _traced_init(init_fn, mesh, seed)
  schedule = (num_epochs, checkpoint_every, keep)
  run_meta = _run_meta(workdir, data, m, batch_size, seed, fingerprint, schedule)
  workdir = Path(workdir)
  workdir.mkdir(parents=True, exist_ok=True)
  data = {k: np.asarray(v) for k, v in data.items()}
  run = EpochRunner(workdir, step_fn, data, batch_size, seed, run_meta, mesh)
  with (
      checkpointing.Checkpoints(workdir / layout.CHECKPOINTS, keep=keep) as ckpts,
      preemption.Signals() as signals,
  ):
    state, start, metrics = run.start(ckpts, init, on_start)
    with preemption.PeerWatch(workdir / layout.CHECKPOINTS) as watch:
      try:
        state = run.epochs(
            state, start, metrics, num_epochs, ckpts, signals, checkpoint_every, epoch_end_fn, desc
        )
      except Exception as e:  # with several processes a dead peer ends this one here
        watch.settle(e)
        raise
  if signals.received is not None:  # arrived during the last save: stop as asked
    raise signals.stopped(f"the run finished ({num_epochs} epochs)")
  return sharding.local_copy(state)
