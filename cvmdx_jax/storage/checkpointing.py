"""Checkpoints of arbitrary pytrees of arrays; the only module that imports orbax.

Wraps the orbax V1 training `Checkpointer`: step directories `<root>/<step>` are written
to a temporary name and renamed when complete (orbax), each holding the state and a JSON
metadata dict (the run's fingerprint). A step directory without the commit marker orbax
writes last, or a leftover temporary directory, is never loaded. Every failure a user can
cause (no checkpoint, other fingerprint, other shapes, garbled files) is raised as
`CheckpointMismatchError` naming the directory and the mismatch. After orbax has committed a
step, `<step>/checksums.json` records the sha256 of every file it wrote (the package's one
checksum scheme, `storage.checksums`); `load` verifies all of them first, so a flipped byte
anywhere in a step, even one orbax still decodes, is refused naming the file. orbax's INFO
logging is silenced while orbax runs (`_quiet_orbax`), not for the whole process; during a
save its warnings and errors are held back, re-logged if the save succeeds and dropped if it
fails (the exception, passed on, says what went wrong). A failed save removes orbax's
temporary directories (`*.orbax-checkpoint-tmp*`), and a writable `Checkpoints` removes any
left by a killed process when it opens its root (callers hold the workdir lock by then),
together with a committed step that has no checksums.json yet: a kill between orbax's commit
and the manifest. The run then resumes from the step before, never from unverified files; a
read-only `Checkpoints` lists such a step, and `load` refuses it naming the missing manifest.
"""

import contextlib
import copy
import functools
import logging
import os
import shutil
import threading
import time
from pathlib import Path
from typing import Any

import jax
import orbax.checkpoint.experimental.v1 as ocp

from cvmdx_jax.storage import checksums, identity
from cvmdx_jax.storage.checkpoint_checks import (
    CheckpointMismatchError,
    check_structure,
    refuse_nan,
)

__all__ = ["CheckpointMismatchError", "Checkpoints", "check_structure", "load_latest"]

# orbax writes this file into the temporary directory just before the final rename; a
# step directory without it was not finished by orbax (or was tampered with).
_COMMIT_MARKER = "commit_success.txt"
_STATE = "state"  # the checkpointable (subdirectory) that holds the state pytree
_TMP_MARK = ".orbax-checkpoint-tmp"  # in the name of every directory orbax has not finished


class _QuietOrbax(logging.Filter):
  """Drops orbax's INFO/DEBUG records from the absl logger; warnings and errors pass, or,
  with a `held` list, are appended to it instead."""

  def __init__(self, held: list | None = None):
    super().__init__()
    self.held = held

  def filter(self, record: logging.LogRecord) -> bool:
    if "orbax" not in record.pathname:
      return True
    if record.levelno < logging.WARNING:
      return False
    if self.held is None:
      return True
    self.held.append(record)
    return False


@contextlib.contextmanager
def _quiet_orbax(held: list | None = None):
  """Installs `_QuietOrbax(held)` on the absl logger for the duration of the block."""
  logger, quiet = logging.getLogger("absl"), _QuietOrbax(held)
  logger.addFilter(quiet)
  try:
    yield
  finally:
    logger.removeFilter(quiet)


@contextlib.contextmanager
def _holding_orbax_logs():
  """`_quiet_orbax` that holds orbax's warnings and errors back: re-logged when the block
  succeeds, dropped when it raises (the exception says what went wrong)."""
  held = []
  with _quiet_orbax(held):
    yield
  for record in held:
    logging.getLogger("absl").handle(record)


def _remove_temporaries(root: Path) -> None:
  """Deletes orbax's unfinished directories directly under `root` (process 0 only)."""
  if jax.process_index() == 0 and root.is_dir():
    for p in root.glob(f"*{_TMP_MARK}*"):
      shutil.rmtree(p, ignore_errors=True)


def _join_orbax_threads(timeout_s: float = 60.0) -> None:
  """Waits (at most `timeout_s` in all) for orbax's background threads to end, so that
  none writes into a temporary directory after it has been removed."""
  deadline = time.monotonic() + timeout_s
  for thread in threading.enumerate():
    if thread is not threading.current_thread() and type(thread).__module__.startswith("orbax"):
      try:
        thread.join(max(0.0, deadline - time.monotonic()))
      except Exception:  # pylint: disable=broad-except
        pass  # orbax's threads re-raise their error on join: the failed save's, passed on


def _complete_steps(root: Path, *, with_manifest: bool = False) -> tuple[list[int], list[Path]]:
  """(sorted steps with a commit marker, and with `with_manifest` also a checksums.json;
  the other step directories)."""
  done, partial = [], []
  for p in root.iterdir() if root.is_dir() else ():
    if p.is_dir() and p.name.isdigit():
      complete = (p / _COMMIT_MARKER).is_file() and (
          not with_manifest or (p / checksums.MANIFEST).is_file()
      )
      (done if complete else partial).append(p)
  return sorted(int(p.name) for p in done), partial


class Checkpoints:
  """The complete checkpoints under one directory; saving keeps the latest `keep`.

  Use as a context manager. With `writable=False` nothing on disk is created or removed;
  with `writable=True` unfinished step and temporary directories are deleted on opening.
  """

  def __init__(self, root: str | os.PathLike, *, keep: int | None = None, writable: bool = True):
    self.root = Path(root).absolute()  # orbax requires absolute paths
    self._steps, partial = _complete_steps(self.root, with_manifest=writable)
    self._ckptr, self._failed = None, False
    if not writable:
      return
    for p in partial if jax.process_index() == 0 else ():  # one process cleans up
      shutil.rmtree(p)
    _remove_temporaries(self.root)
    policy = ocp.training.preservation_policies
    try:
      with _quiet_orbax():
        self._ckptr = ocp.training.Checkpointer(
            self.root,
            preservation_policy=policy.LatestN(keep) if keep else None,
            cleanup_tmp_directories=True,
        )
    except Exception as e:  # orbax reads every step's metadata here
      raise CheckpointMismatchError(
          f"checkpoint directory {self.root} holds an unreadable checkpoint "
          f"({type(e).__name__}: {e})"
      ) from e

  def __enter__(self) -> "Checkpoints":
    return self

  def __exit__(self, *exc) -> None:
    if self._ckptr is not None:
      with _holding_orbax_logs():
        self._ckptr.close()

  @property
  def latest_epoch(self) -> int | None:
    """The highest complete step, or None when there is none: an epoch, as every trainer
    saves one step per epoch, named by its number."""
    return self._steps[-1] if self._steps else None

  def save(self, step: int, state: Any, metadata: Any) -> None:
    """Writes `state` (a pytree of arrays) and JSON `metadata` as `step`; blocks until done.

    On failure the exception is passed on, orbax's log records of the save are dropped and
    its temporary directories removed; earlier steps are untouched. Saving again after a
    failure needs a new `Checkpoints`.
    """
    if self._failed:
      raise ValueError(f"Checkpoints({self.root}): an earlier save failed; open it again")
    if self._ckptr is None:
      raise ValueError(f"Checkpoints({self.root}) was opened read-only")
    custom = {"cvmdx": identity.to_json(metadata, "checkpoint metadata")}
    try:
      with _holding_orbax_logs():
        self._ckptr.save(
            step,
            state,
            checkpointable_name=_STATE,
            force=True,
            overwrite=True,
            custom_metadata=custom,
        )
        self._ckptr.wait()
    except BaseException:
      self._failed = True
      self._close_after_failure()
      raise
    if jax.process_index() == 0:  # orbax has committed every process's files
      checksums.record_tree(self.root / str(step))
    self._steps = _complete_steps(self.root)[0]

  def _close_after_failure(self) -> None:
    """Closes orbax's checkpointer, then removes its temporary directories.

    Orbax's metadata thread may still write into the failed step's temporary directory
    after the error has surfaced. The first `close` raises that error again before joining
    the thread (orbax 0.12); a second one joins it. Its other background threads (the one
    that writes `_sharding`, on a full disk still running after both) are joined before
    the directories go.
    """
    ckptr, self._ckptr = self._ckptr, None
    for _ in range(2):
      try:
        with _quiet_orbax([]):
          ckptr.close()
        break
      except Exception:  # the failed save's error, which `save` is passing on
        continue
    _join_orbax_threads()
    _remove_temporaries(self.root)

  def load(self, step: int, abstract_state: Any, *, partial: bool = False) -> tuple[Any, Any]:
    """Restores `step` into the structure, shapes and shardings of `abstract_state`.

    Args:
      step: a complete step (see `latest_epoch`).
      abstract_state: pytree of `jax.ShapeDtypeStruct` (with `sharding`) to restore into.
      partial: restore only the leaves of `abstract_state` (e.g. the parameters without
        the optimiser state); other leaves of the checkpoint are not read.

    Returns:
      (state, metadata): the restored pytree and the JSON metadata saved with it.

    Raises:
      CheckpointMismatchError: the step is missing, garbled, a file differs from its
        sha256, or its leaves differ from `abstract_state` (the message names the leaf
        and both shapes).
    """
    where = self.root / str(step)
    if step not in self._steps:
      raise CheckpointMismatchError(f"no complete checkpoint {where}")
    try:
      checksums.verify_tree(where)
    except checksums.CorruptRunError as e:
      raise CheckpointMismatchError(
          f"checkpoint {where} is corrupt: {e}; delete this step directory to fall back to "
          "an older one, or retrain"
      ) from e
    meta = _state_metadata(where, (where / checksums.MANIFEST).read_bytes())
    check_structure(meta.metadata, abstract_state, str(where), partial)
    context = ocp.Context()
    context.pytree.loading.partial_load = partial
    try:
      with _quiet_orbax(), context:
        state = ocp.load(where, abstract_state, checkpointable_name=_STATE)
      jax.block_until_ready(state)
    except Exception as e:
      raise CheckpointMismatchError(
          f"checkpoint {where} is corrupt or unreadable ({type(e).__name__})"
      ) from e
    custom = meta.custom_metadata or {}
    if "cvmdx" not in custom:
      raise CheckpointMismatchError(f"checkpoint {where} carries no cvmdx metadata")
    refuse_nan(state, where)
    return state, copy.deepcopy(custom["cvmdx"])


@functools.lru_cache(maxsize=64)
def _state_metadata(where: Path, manifest: bytes):
  """orbax's metadata of step directory `where` (its state's leaves with shapes and dtypes,
  and the custom metadata), read once per step content: `manifest` is the step's verified
  checksums.json, so a step rewritten in place is read again. orbax opens every saved array
  for it (~1 s for a distilled student's state on 2 CPU cores), and one process reads a
  checkpoint several times (the tokeniser in every stage of `make demo`)."""
  try:
    with _quiet_orbax():
      meta = ocp.metadata(where, _STATE)
    if meta.metadata is None:  # orbax returns None when it cannot parse the tree metadata
      raise ValueError("no readable pytree metadata")
  except Exception as e:
    raise CheckpointMismatchError(
        f"checkpoint {where} is corrupt or unreadable ({type(e).__name__}: {e})"
    ) from e
  return meta


def load_latest(
    root: str | os.PathLike, abstract_state: Any, *, partial: bool = False
) -> tuple[Any, Any]:
  """Restores the latest complete step under `root` (see `Checkpoints.load`).

  Raises:
    CheckpointMismatchError: no complete checkpoint, or `Checkpoints.load`'s reasons.
  """
  ckpts = Checkpoints(root, writable=False)
  if ckpts.latest_epoch is None:
    raise CheckpointMismatchError(f"no complete checkpoint under {ckpts.root}")
  return ckpts.load(ckpts.latest_epoch, abstract_state, partial=partial)
