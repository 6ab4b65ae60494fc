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

import json
import os
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import jax
import numpy as np
from tqdm.auto import tqdm

from cvmdx_jax import sharding
from cvmdx_jax.runs import layout
from cvmdx_jax.storage import atomic, checkpointing, identity, locking
from cvmdx_jax.storage.checkpointing import CheckpointMismatchError
from cvmdx_jax.train import preemption

State = Any
Batch = dict[str, jax.Array]
StepFn = Callable[[State, Batch, jax.Array], tuple[State, dict[str, jax.Array]]]

# init_fn gets this fold of the seed's key; global steps (fold_in data) never reach it.
_INIT_FOLD = 2**32 - 1
_FINITE_METRICS = ("loss", "grad_norm")


class TrainingError(RuntimeError):
  """Training produced a non-finite loss or gradient norm."""


def init_key(seed: int) -> jax.Array:
  """The key `train` passes to `init_fn` for `seed`."""
  return jax.random.fold_in(jax.random.key(seed), _INIT_FOLD)


def _abstract_state(init_fn: Callable[[jax.Array], State], mesh) -> State:
  """Shapes and dtypes of `init_fn`'s state, replicated on `mesh`; refuses typed PRNG keys."""
  abstract = jax.eval_shape(init_fn, init_key(0))
  for path, leaf in jax.tree_util.tree_flatten_with_path(abstract)[0]:
    if jax.dtypes.issubdtype(leaf.dtype, jax.dtypes.prng_key):
      raise ValueError(
          f"init_fn state leaf {jax.tree_util.keystr(path)} is a PRNG key; keep "
          "keys out of the train state (train derives them from seed and step)"
      )
  rep = sharding.replicated(mesh)
  return jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=rep), abstract)


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


def _trim_metrics(path: Path, epochs_done: int) -> None:
  """Keeps only complete lines of epochs <= epochs_done (a resumed run rewrites the rest)."""
  if not path.exists():
    return
  kept = []
  for line in path.read_text().splitlines():
    try:
      record = json.loads(line)
      if record["epoch"] <= epochs_done:
        kept.append(record)
    except (ValueError, KeyError, TypeError):
      continue
  atomic.write_jsonl(path, kept)


def _check_finite(metrics: list[dict[str, np.ndarray]], epoch: int, first_step: int) -> None:
  """TrainingError at the first non-finite loss or grad_norm of an epoch's step metrics."""
  for i, m in enumerate(metrics):
    for name in _FINITE_METRICS:
      if name in m and not np.isfinite(m[name]):
        raise TrainingError(
            f"non-finite {name}={float(m[name])} at global step "
            f"{first_step + i} (epoch {epoch}); last good checkpoint kept"
        )


def _epoch_summary(
    metrics: list[dict[str, np.ndarray]], weights: np.ndarray, epoch: int, first_step: int
) -> dict[str, float]:
  """Weighted means of per-step metrics; TrainingError at the first non-finite loss/grad."""
  _check_finite(metrics, epoch, first_step)
  n = weights.sum(axis=1)
  return {
      k: float(np.sum(n * np.array([m[k] for m in metrics], np.float64)) / n.sum())
      for k in metrics[0]
  }


def _to_json_value(value: Any) -> Any:
  return np.asarray(jax.device_get(value)).tolist()


def _epoch_order(seed: int, epoch: int, m: int, batch_size: int) -> tuple[np.ndarray, np.ndarray]:
  """(example indices, weights), both (steps per epoch, batch_size), of 0-based `epoch`."""
  order = np.random.default_rng([seed, epoch]).permutation(m)
  order, weight = sharding.pad_batch(order, batch_size)
  return order.reshape(-1, batch_size), weight.reshape(-1, batch_size)


def _resume_point(
    ckpts, workdir: Path, abstract: State, run_meta: dict, steps_per_epoch: int
) -> tuple[State | None, int, list[dict]]:
  """(state or None, global step, the step metrics of its unfinished epoch) to resume from:
  the latest epoch checkpoint, or a later preemption checkpoint."""
  done, state = ckpts.latest_epoch or 0, None
  if done:
    state, saved = ckpts.load(done, abstract)
    identity.check(saved, run_meta, f"checkpoint {ckpts.root / str(done)}", CheckpointMismatchError)
  stopped = preemption.load_stopped(workdir, abstract, run_meta, done * steps_per_epoch)
  return stopped or (state, done * steps_per_epoch, [])


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
  if not locking.is_held(workdir):
    raise ValueError(
        f"train: workdir {workdir} is not held; call train inside " "storage.locking.hold(workdir)"
    )
  m = _check_data(data, batch_size)
  if checkpoint_every < 1 or keep < 1:
    raise ValueError(f"train: checkpoint_every={checkpoint_every} and keep={keep} must be >= 1")
  mesh = sharding.data_mesh()
  sharding.check_divisible(batch_size, mesh)
  abstract = _abstract_state(init_fn, mesh)
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
            "schedule": [num_epochs, checkpoint_every, keep],
        },
        f"run (workdir {workdir})",
    )
  workdir = Path(workdir)
  workdir.mkdir(parents=True, exist_ok=True)
  run = _Run(
      workdir,
      init_fn,
      step_fn,
      {k: np.asarray(v) for k, v in data.items()},
      batch_size,
      seed,
      run_meta,
      mesh,
  )
  with (
      checkpointing.Checkpoints(workdir / layout.CHECKPOINTS, keep=keep) as ckpts,
      preemption.Signals() as signals,
  ):
    state, start, metrics = run.start(ckpts, abstract, on_start)
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


class _Run:
  """The fixed parts of one `train` call and its two phases: `start` and `epochs`."""

  def __init__(
      self,
      workdir: Path,
      init_fn,
      step_fn: StepFn,
      data: dict[str, np.ndarray],
      batch_size: int,
      seed: int,
      run_meta: dict,
      mesh,
  ):
    self.workdir, self.init_fn, self.data, self.mesh = workdir, init_fn, data, mesh
    self.batch_size, self.seed, self.run_meta = batch_size, seed, run_meta
    self.m = next(iter(data.values())).shape[0]
    self.steps_per_epoch = -(-self.m // batch_size)
    root_key = jax.random.key(seed)

    def keyed_step(state, batch, global_step):
      return step_fn(state, batch, jax.random.fold_in(root_key, global_step))

    self.step = jax.jit(keyed_step, donate_argnums=0)

  def start(self, ckpts, abstract: State, on_start) -> tuple[State, int, list[dict]]:
    """(state, global step, step metrics of the unfinished epoch) to go on from."""
    state, start, metrics = _resume_point(
        ckpts, self.workdir, abstract, self.run_meta, self.steps_per_epoch
    )
    if state is None:
      state = jax.jit(self.init_fn, out_shardings=sharding.replicated(self.mesh))(
          init_key(self.seed)
      )
    if on_start is not None:
      on_start()
    if sharding.is_primary():
      _trim_metrics(self.workdir / layout.METRICS, start // self.steps_per_epoch)
    return state, start, metrics

  def epochs(
      self,
      state: State,
      start: int,
      metrics: list,
      num_epochs: int,
      ckpts,
      signals: preemption.Signals,
      checkpoint_every: int,
      epoch_end_fn,
      desc: str,
  ) -> State:
    """Runs the epochs from global step `start` to `num_epochs`; `metrics` holds the step
    metrics of `start`'s epoch before `start`."""
    spe, primary = self.steps_per_epoch, sharding.is_primary()
    saved = (ckpts.latest_epoch or 0) * spe  # the global step of the newest checkpoint
    with tqdm(
        total=num_epochs * spe,
        initial=min(start, num_epochs * spe),
        desc=desc,
        unit="step",
        dynamic_ncols=True,
        disable=not primary,
    ) as bar:
      for epoch in range(start // spe, num_epochs):
        begin, first_step = time.perf_counter(), epoch * spe
        order, weight = _epoch_order(self.seed, epoch, self.m, self.batch_size)
        for i in range(max(start - first_step, 0), spe):
          if signals.stop_at(first_step + i):
            raise self._stop(signals, first_step + i, saved, state, metrics)
          batch = {k: v[order[i]] for k, v in self.data.items()}
          batch["weight"] = weight[i]
          state, step_metrics = self.step(
              state, sharding.shard_batch(batch, self.mesh), first_step + i
          )
          metrics.append(step_metrics)
          bar.update()
        summary = _epoch_summary(jax.device_get(metrics), weight, epoch + 1, first_step)
        metrics = []
        if epoch_end_fn is not None:
          summary.update(
              {
                  k: _to_json_value(v)
                  for k, v in epoch_end_fn(sharding.local_copy(state), epoch + 1).items()
              }
          )
        bar.set_postfix(loss=f"{summary['loss']:.4g}", epoch=epoch + 1)
        line = {
            "epoch": epoch + 1,
            "step": first_step + spe,
            "seconds": round(time.perf_counter() - begin, 4),
            **summary,
        }
        if primary:
          atomic.append_jsonl(self.workdir / layout.METRICS, line)
        if (epoch + 1) % checkpoint_every == 0 or epoch + 1 == num_epochs:
          ckpts.save(epoch + 1, state, self.run_meta)
          saved = first_step + spe
          preemption.drop_stopped(self.workdir)
    return state

  def _stop(
      self, signals: preemption.Signals, step: int, saved: int, state: State, metrics: list
  ) -> preemption.Stopped:
    """Saves the state before global `step` (unless a checkpoint holds it already) and
    returns the `Stopped` to raise."""
    spe = self.steps_per_epoch
    if step != saved:
      host_metrics = jax.device_get(metrics)
      _check_finite(host_metrics, step // spe + 1, step // spe * spe)
      preemption.save_stopped(self.workdir, step, state, self.run_meta, host_metrics)
      where = (
          f"saved global step {step} (epoch {step // spe + 1}, step {step % spe + 1}) "
          f"in {self.workdir / preemption.STOPPED}"
      )
    else:
      where = f"the last checkpoint holds global step {step}"
    return signals.stopped(where)
