"""Run directories owned by one process: an OS file lock inside every workdir a command writes.

`hold(workdir)` takes `fcntl.flock(LOCK_EX | LOCK_NB)` on `<workdir>/.lock` before anything
is written to the directory and writes "<pid> <host>" into that file; a second process gets
`WorkdirLockedError` naming the holder. The OS drops the lock when the holder exits or is
killed (kill -9 included), so a stale lock file never blocks a rerun. Holds nest within one
process; `is_held` tells code that needs its caller's hold (`train.loop.train`). When the
directory holds nothing but the lock file afterwards, the lock file is removed (and the
directory too when `hold` created it), so a run refused for bad input leaves no trace.

Several processes of one `jax.distributed` run (a shared workdir): process i locks
`<workdir>/.lock` (i = 0) or `<workdir>/.lock.<i>`, so a second run, single- or
multi-process, is refused by the lock of its process 0 at least. The processes then tell each
other whether they got their lock (one allgather) and all raise together if any did not, so
none of them goes on to write while another gives up.
"""

import contextlib
import fcntl
import functools
import inspect
import os
import socket
import sys
from collections.abc import Callable, Iterator
from pathlib import Path

from cvmdx_jax.errors import UserError

LOCK_NAME = ".lock"

_held: dict[Path, list] = {}  # lock file -> [fd, nesting depth] of this process


class WorkdirError(UserError):
  """A workdir cannot be used (not creatable, no lock file possible)."""


class WorkdirLockedError(WorkdirError):
  """Another process holds the workdir's lock."""


def _process() -> tuple[int, int]:
  """(process index, process count); (0, 1) unless `jax.distributed` was initialised."""
  jax = sys.modules.get("jax")  # not imported: no distributed run (and no need to import it)
  if jax is None or not jax.distributed.is_initialized():
    return 0, 1
  return jax.process_index(), jax.process_count()


def lock_path(workdir: str | os.PathLike, process_index: int = 0) -> Path:
  """The lock file process `process_index` takes in `workdir`."""
  name = LOCK_NAME if process_index == 0 else f"{LOCK_NAME}.{process_index}"
  return Path(workdir).absolute() / name


def holder(path: str | os.PathLike) -> str:
  """Who wrote the lock file `path` last: "pid <pid> on <host>" (or "an unknown process")."""
  try:
    pid, host = Path(path).read_text().split()
    return f"pid {int(pid)} on {host}"
  except (OSError, ValueError):
    return "an unknown process"


def is_held(workdir: str | os.PathLike) -> bool:
  """Whether this process holds `workdir` (`hold`)."""
  return lock_path(workdir, _process()[0]) in _held


def _try_lock(path: Path) -> int | None:
  """An fd holding the lock on `path`, or None when another process holds it."""
  while True:
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
      fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
      os.close(fd)
      return None
    try:  # the file may have been unlinked by its last holder meanwhile: lock the new one
      if os.stat(path).st_ino == os.fstat(fd).st_ino:
        return fd
    except FileNotFoundError:
      pass
    os.close(fd)


def _agree(ok: bool, count: int) -> bool:
  """True when every process of the run got its lock (all must call this together)."""
  if count == 1:
    return ok
  import numpy as np
  from jax.experimental import multihost_utils

  return bool(np.all(multihost_utils.process_allgather(np.int32(ok))))


@contextlib.contextmanager
def hold(workdir: str | os.PathLike) -> Iterator[Path]:
  """Holds `workdir`'s lock (created with its parents if missing) for the `with` block.

  Args:
    workdir: the run directory.

  Yields:
    The lock file.

  Raises:
    WorkdirLockedError: another process holds it; the message names its pid and host.
    WorkdirError: the directory or its lock file cannot be created.
  """
  index, count = _process()
  path = lock_path(workdir, index)
  if path in _held:
    _held[path][1] += 1
    try:
      yield path
    finally:
      _held[path][1] -= 1
    return
  created = not path.parent.exists()
  try:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = _try_lock(path)
  except OSError as e:
    raise WorkdirError(
        f"workdir {path.parent}: cannot create its lock file {path.name} " f"({e.strerror or e})"
    ) from e
  if not _agree(fd is not None, count):
    if fd is not None:  # ours, but the run stops: leave the directory as it was
      path.unlink()
      os.close(fd)
      raise WorkdirLockedError(
          f"workdir {path.parent} is locked by another process of a "
          "second run; nothing was written"
      )
    raise WorkdirLockedError(
        f"workdir {path.parent} is in use by {holder(path)} (lock file {path}); wait for that "
        "run to finish or choose another workdir"
    )
  try:
    os.ftruncate(fd, 0)
    os.write(fd, f"{os.getpid()} {socket.gethostname()}\n".encode())
    _held[path] = [fd, 1]
    yield path
  finally:
    _held.pop(path, None)
    if [p.name for p in path.parent.iterdir()] == [path.name]:  # nothing else written
      path.unlink()
      if created:
        with contextlib.suppress(OSError):
          path.parent.rmdir()
    os.close(fd)


def holds(arg: str) -> Callable:
  """Decorator: each call of the function runs inside `hold(<its argument named arg>)`."""

  def decorate(fn: Callable) -> Callable:
    signature = inspect.signature(fn)

    @functools.wraps(fn)
    def locked(*args, **kwargs):
      bound = signature.bind(*args, **kwargs)
      bound.apply_defaults()
      with hold(bound.arguments[arg]):
        return fn(*args, **kwargs)

    return locked

  return decorate
