"""The epochs of one `loop.train` call: resume point, example order, steps, metrics lines,
checkpoints and the stop at a step boundary.

`EpochRunner` holds a call's fixed parts; epoch e (0-based) visits the examples in the order
`np.random.default_rng([seed, e]).permutation(M)` (padded to whole batches, `epoch_order`)
and global step g gets the key `jax.random.fold_in(jax.random.key(seed), g)`.
"""

import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import numpy as np
from tqdm.auto import tqdm

from cvmdx_jax import sharding
from cvmdx_jax.runs import layout
from cvmdx_jax.storage import atomic, identity
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


def steps_per_epoch(num_examples: int, batch_size: int) -> int:
  """Global steps of one epoch over `num_examples` (the last batch padded)."""
  return -(-num_examples // batch_size)


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


class EpochRunner:
  """The fixed parts of one `train` call and its two phases: `start` and `epochs`."""

  def __init__(
      self,
      workdir: Path,
      step_fn: StepFn,
      data: dict[str, np.ndarray],
      batch_size: int,
      seed: int,
      run_meta: dict,
      mesh,
  ):
    self.workdir, self.data, self.mesh = workdir, data, mesh
    self.batch_size, self.seed, self.run_meta = batch_size, seed, run_meta
    self.m = next(iter(data.values())).shape[0]
    self.steps_per_epoch = steps_per_epoch(self.m, batch_size)
    root_key = jax.random.key(seed)

    def keyed_step(state, batch, global_step):
      return step_fn(state, batch, jax.random.fold_in(root_key, global_step))

    self.step = jax.jit(keyed_step, donate_argnums=0)

  def start(self, ckpts, init, on_start) -> tuple[State, int, list[dict]]:
    """(state, global step, step metrics of the unfinished epoch) to go on from; `init` is
    the init function traced for this run's key (`jax.stages.Traced`, its `out_info` the
    state to restore into)."""
    state, start, metrics = _resume_point(
        ckpts, self.workdir, init.out_info, self.run_meta, self.steps_per_epoch
    )
    if state is None:
      state = init.lower().compile()(init_key(self.seed))
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
