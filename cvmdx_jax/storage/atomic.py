"""Atomic file writes, the one way every module of the package writes a file.

`writing(path)` hands out a hidden temporary file beside `path`; when the block ends
without an exception the temporary is renamed over `path` (`os.replace`, atomic on
POSIX), otherwise it is removed. A reader therefore sees the old file or the new one,
never a half-written one, and an existing file survives a crash or a failing writer.
The temporary is created like a plain `open()` creates a file (mode 0o666 filtered by
the process umask, e.g. 0o644 under umask 022), so results can be shared as usual.

Format helpers: `write_bytes`, `write_text`, `write_json` (text of `json_text`),
`write_jsonl`, `write_npz`, `write_mat`; `write_all` writes several files as a group (all
new or all old); `append_jsonl` appends one line to a log. JSON is strict (RFC 8259, what
every parser reads): a float that is NaN or infinite (a metric of an empty class, a
diverged loss) is written as `null`, never as the bare `NaN` / `Infinity` of Python's
json module.
"""

import contextlib
import json
import math
import os
import secrets
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import IO, Any

import numpy as np
import scipy.io


@contextlib.contextmanager
def writing(path: str | os.PathLike, mode: str = "wb") -> Iterator[IO]:
  """Opens a temporary beside `path` for writing; renames it over `path` on success.

  Args:
    path: the target file; its directory must exist.
    mode: "wb" (binary) or "w" (text, UTF-8).

  Yields:
    The open temporary file.
  """
  if mode not in ("wb", "w"):
    raise ValueError(f"atomic.writing: mode={mode!r}, expected 'wb' or 'w'")
  path = Path(path)
  tmp = path.with_name(f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp")
  # O_EXCL: never reuse a name; 0o666 & ~umask: what a plain open() would create.
  fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
  try:
    with os.fdopen(fd, mode, **({"encoding": "utf-8"} if mode == "w" else {})) as f:
      yield f
    os.replace(tmp, path)
  except BaseException:
    tmp.unlink(missing_ok=True)
    raise


def write_bytes(path: str | os.PathLike, data: bytes) -> None:
  with writing(path) as f:
    f.write(data)


def write_text(path: str | os.PathLike, text: str) -> None:
  with writing(path, "w") as f:
    f.write(text)


def write_all(files: dict[str | os.PathLike, bytes]) -> None:
  """Writes {path: bytes}: every file to its temporary (flushed) before any is renamed,
  the first path renamed last. A failure while writing (a full disk) leaves every old
  file, or none, in place and no temporary."""
  with contextlib.ExitStack() as stack:
    for path, data in files.items():
      f = stack.enter_context(writing(path))
      f.write(data)
      f.flush()


def _finite_json(value: Any) -> Any:
  """`value` with every non-finite float (also a numpy float64) in its dicts, lists and
  tuples replaced by None (JSON null)."""
  if isinstance(value, float):
    return value if math.isfinite(value) else None
  if isinstance(value, dict):
    return {k: _finite_json(v) for k, v in value.items()}
  if isinstance(value, (list, tuple)):
    return [_finite_json(v) for v in value]
  return value


def _dumps(value: Any, **kwargs) -> str:
  """Strict JSON text of `value` (module docstring)."""
  return json.dumps(_finite_json(value), allow_nan=False, **kwargs)


def json_text(value: Any, **kwargs) -> str:
  """`value` as strict JSON (indent 2 unless `kwargs` say otherwise) and a final newline."""
  return _dumps(value, **{"indent": 2, **kwargs}) + "\n"


def write_json(path: str | os.PathLike, value: Any, **kwargs) -> None:
  """`json_text(value, **kwargs)` to `path`."""
  write_text(path, json_text(value, **kwargs))


def write_jsonl(path: str | os.PathLike, records: Iterable[Any]) -> None:
  """Rewrites `path` with one compact JSON line per record."""
  write_text(path, "".join(_dumps(r) + "\n" for r in records))


def append_jsonl(path: str | os.PathLike, record: Any) -> None:
  """Appends one JSON line to a log with a single `write` on an O_APPEND descriptor.

  Earlier lines are never touched; a crash can at most leave the new line cut short,
  which readers of the log skip (e.g. `train.loop` on resume, via `write_jsonl`).
  """
  data = (_dumps(record) + "\n").encode()
  fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o666)
  try:
    while data:
      data = data[os.write(fd, data) :]
  finally:
    os.close(fd)


def write_npz(path: str | os.PathLike, **arrays) -> None:
  """Arrays as an uncompressed .npz (`np.savez`)."""
  with writing(path) as f:
    np.savez(f, **arrays)


def write_mat(path: str | os.PathLike, mat: dict) -> None:
  """A dict of arrays as a MATLAB 5 .mat file (`scipy.io.savemat`)."""
  with writing(path) as f:
    scipy.io.savemat(f, mat)
