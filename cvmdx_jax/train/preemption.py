"""How a training run stops on a signal or a lost peer (`train.loop` uses it).

Preemption: a cluster preempts a job (Slurm, Kubernetes eviction) by sending SIGTERM to
every process; Ctrl-C sends SIGINT. While `Signals` is entered, such a signal is recorded,
not acted on at once: the loop stops at the next step boundary that every process agrees
on, saves a checkpoint there and raises `Stopped`, which exits with status 143 (SIGTERM,
`PREEMPTED_STATUS`, what a requeue expects) or 130 (SIGINT). A second SIGINT interrupts
at once (KeyboardInterrupt). One process: Python signal handlers. Several processes
(`jax.distributed`): JAX's preemption notifier owns SIGTERM; `stop_at` asks JAX's
preemption sync manager (`multihost_utils.reached_preemption_sync_point`), which makes all
processes stop at the same step; SIGINT is passed on to it as a SIGTERM to the process.

A lost peer (another process of a `jax.distributed` run killed, out of memory, ...): the
JAX runtime can no longer shut down cleanly (it waits for the dead peer, then aborts with a
stack trace). A collective that fails, or `PeerWatch` finding a peer silent, calls
`lost_peer`, which prints one line and exits at once.
"""

import os
import shutil
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any

import jax
import numpy as np

from cvmdx_jax import sharding
from cvmdx_jax.storage import checkpointing, identity

PREEMPTED_STATUS = 128 + signal.SIGTERM  # 143
INTERRUPTED_STATUS = 128 + signal.SIGINT  # 130
PEER_LOST_STATUS = 75  # EX_TEMPFAIL: a process of the run died; rerun every process
STOPPED = "preempted"  # <workdir>/preempted/<global step>/: the state a signal stopped at


class Stopped(SystemExit):
  """The run stopped on a signal after saving; `code` is the exit status, `message` says
  where it stopped."""

  def __init__(self, message: str, status: int):
    super().__init__(status)
    self.message = message


class Signals:
  """Records SIGTERM and SIGINT while entered (main thread only; elsewhere a no-op) and
  restores the previous handlers on exit. `received` is the first signal number or None."""

  def __init__(self):
    self.received: int | None = None
    self._previous: dict[int, object] = {}
    self._multi = False

  def __enter__(self) -> "Signals":
    if threading.current_thread() is not threading.main_thread():
      return self
    self._multi = jax.process_count() > 1
    names = (signal.SIGINT,) if self._multi else (signal.SIGINT, signal.SIGTERM)
    for number in names:
      self._previous[number] = signal.signal(number, self._handle)
    return self

  def __exit__(self, *exc) -> None:
    for number, handler in self._previous.items():
      signal.signal(number, signal.SIG_DFL if handler is None else handler)  # None: not Python's
    self._previous.clear()

  def _handle(self, number: int, frame) -> None:
    del frame
    if self.received == signal.SIGINT and number == signal.SIGINT:
      raise KeyboardInterrupt  # the second Ctrl-C does not wait for a step boundary
    self.received = self.received or number
    if self._multi:  # JAX's preemption notifier starts the agreement on a stop step
      os.kill(os.getpid(), signal.SIGTERM)

  def stop_at(self, global_step: int) -> bool:
    """Whether to stop before `global_step` (all processes call it at every step, with
    the same increasing steps; with several processes they all get the same answer)."""
    if self._multi:
      from jax.experimental import multihost_utils  # pylint: disable=import-outside-toplevel

      return multihost_utils.reached_preemption_sync_point(global_step)
    return self.received is not None

  @property
  def status(self) -> int:
    """The exit status of a stop: 130 after SIGINT, else 143."""
    return INTERRUPTED_STATUS if self.received == signal.SIGINT else PREEMPTED_STATUS

  def stopped(self, where: str) -> Stopped:
    """The `Stopped` to raise once the state at `where` is saved."""
    what = "interrupted" if self.status == INTERRUPTED_STATUS else "preempted (SIGTERM)"
    return Stopped(f"{what}; {where}", self.status)


def save_stopped(
    workdir: Path, step: int, state: Any, run_meta: dict, metrics: list[dict[str, np.ndarray]]
) -> None:
  """Saves the state before global `step` with the step metrics of its unfinished epoch
  under `<workdir>/preempted/<step>` (the newest only; all processes together)."""
  meta = {
      "run": run_meta,
      "metrics": [{k: np.asarray(v).tolist() for k, v in m.items()} for m in metrics],
  }
  with checkpointing.Checkpoints(workdir / STOPPED, keep=1) as ckpts:
    ckpts.save(step, state, meta)


def load_stopped(
    workdir: Path, abstract: Any, run_meta: dict, after: int
) -> tuple[Any, int, list[dict[str, np.ndarray]]] | None:
  """(state, global step, step metrics of its epoch) of `save_stopped`'s checkpoint when
  it is past global step `after`, else None.

  Raises:
    CheckpointMismatchError: it belongs to another run (`run_meta`) or is broken.
  """
  ckpts = checkpointing.Checkpoints(workdir / STOPPED, writable=False)
  step = ckpts.latest_epoch
  if step is None or step <= after:
    return None
  state, saved = ckpts.load(step, abstract)
  identity.check(
      saved.get("run"),
      run_meta,
      f"checkpoint {ckpts.root / str(step)}",
      checkpointing.CheckpointMismatchError,
  )
  return state, step, [{k: np.asarray(v) for k, v in m.items()} for m in saved["metrics"]]


def drop_stopped(workdir: Path) -> None:
  """Removes `save_stopped`'s checkpoint (process 0) once a later epoch checkpoint holds
  the run."""
  if sharding.is_primary() and (workdir / STOPPED).exists():
    shutil.rmtree(workdir / STOPPED)


def lost_peer(cause: str, checkpoints: Path) -> None:
  """Ends this process of a multi-process run that lost a peer: prints `<script>: error:
  ...` (one line: `cause`, the last complete checkpoint under `checkpoints`) to stderr and
  exits at once with `PEER_LOST_STATUS`, skipping the `jax.distributed` shutdown that would
  wait for the dead peer and then abort."""
  epoch = checkpointing.Checkpoints(checkpoints, writable=False).latest_epoch
  sys.stdout.flush()
  print(
      f"{Path(sys.argv[0]).stem}: error: {cause}; another process of this "
      f"{jax.process_count()}-process run probably died; the last complete checkpoint is "
      f"epoch {epoch or 0} in {checkpoints}; rerun every process to resume",
      file=sys.stderr,
      flush=True,
  )
  os._exit(PEER_LOST_STATUS)  # pylint: disable=protected-access


class PeerWatch:
  """While entered with several processes: a daemon thread that posts this process's beat
  to the `jax.distributed` key-value store every `beat_s` seconds and reads the others';
  a peer that has beaten once and then stays silent for `silent_s` seconds (killed, out of
  memory) ends this process through `lost_peer`, whatever its main thread waits for (a
  collective, a checkpoint barrier). JAX's own heartbeat (`sharding.HEARTBEAT_S`) stays
  the backstop, e.g. for a peer that dies before its first beat."""

  def __init__(self, checkpoints: Path, beat_s: float = 1.0, silent_s: float = 10.0):
    self.checkpoints, self.beat_s, self.silent_s = checkpoints, beat_s, silent_s
    self._stop = threading.Event()
    self._thread = None

  def __enter__(self) -> "PeerWatch":
    if jax.process_count() > 1:
      self._thread = threading.Thread(target=self._watch, daemon=True, name="peer-watch")
      self._thread.start()
    return self

  def __exit__(self, *exc) -> None:
    self._stop.set()
    if self._thread is not None:
      self._thread.join()

  def settle(self, error: Exception) -> None:
    """After `error` in the main thread, with several processes: a failed collective
    (`JaxRuntimeError`) ends this process through `lost_peer` at once; for another error
    (e.g. orbax's barrier failing on a dead peer) the watch gets `silent_s` and two beats
    to find a silent peer. Returns otherwise, so that the caller raises `error`."""
    if self._thread is None:
      return
    if isinstance(error, jax.errors.JaxRuntimeError):
      first = (str(error).strip().splitlines() or [type(error).__name__])[0]
      lost_peer(f"a collective failed ({first})", self.checkpoints)
    self._thread.join(timeout=self.silent_s + 2 * self.beat_s)

  def _watch(self) -> None:
    from jax._src import distributed  # pylint: disable=import-outside-toplevel

    client, me = distributed.global_state.client, jax.process_index()
    seen: dict[int, tuple[str, float]] = {}  # peer -> (its last beat, when it changed)
    beat = 0
    while not self._stop.wait(self.beat_s):
      beat += 1
      try:
        client.key_value_set(f"cvmdx/beat/{me}", str(beat), allow_overwrite=True)
      except Exception:  # pylint: disable=broad-except
        continue  # the service is gone: JAX's client stops this process itself
      now = time.monotonic()
      for peer in set(range(jax.process_count())) - {me}:
        try:
          value = client.key_value_try_get(f"cvmdx/beat/{peer}")
        except Exception:  # pylint: disable=broad-except
          continue  # no beat yet (or the service is gone)
        if seen.get(peer, (None,))[0] != value:
          seen[peer] = (value, now)
        elif now - seen[peer][1] > self.silent_s:
          lost_peer(
              f"process {peer} sent no beat for {now - seen[peer][1]:.0f} s", self.checkpoints
          )
