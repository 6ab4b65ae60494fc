"""The one checksum scheme of the package.

Checksums: one `checksums.json` manifest per directory, used by run directories, the
dataset cache (`data.cache`) and every checkpoint step (`storage.checkpointing`).

Every checksummed file `<dir>/<name>` has the entry `name -> sha256 hex digest` in
`<dir>/checksums.json`. `write_bytes` records the digest of the new content around the
atomic replacement of the file: first the entry lists the old and the new digest, then
only the new one, so a crash at any point leaves a file whose digest is listed.
`read_bytes` verifies the digest and raises `CorruptRunError` naming the file when the
bytes differ (a flipped byte, a truncated copy, an edit by hand). A file without an entry
is refused like a corrupt one. `record_tree` / `verify_tree` do the same for every file
below a directory that another writer (orbax) made, with relative paths as names.

Format helpers: `write_json` / `read_json`, `write_npz` / `read_npz`.
"""

import contextlib
import hashlib
import io
import json
import os
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from cvmdx_jax.errors import UserError
from cvmdx_jax.storage import atomic

MANIFEST = "checksums.json"
_CHUNK = 1 << 20


class CorruptRunError(UserError):
  """A run file's content differs from its recorded checksum, or cannot be parsed."""


def sha256(data: bytes) -> str:
  """The hex sha256 digest of `data`."""
  return hashlib.sha256(data).hexdigest()


def file_sha256(path: str | os.PathLike) -> str:
  """The hex sha256 of a file's bytes, read in 1 MiB chunks."""
  digest = hashlib.sha256()
  with open(path, "rb") as handle:
    while chunk := handle.read(_CHUNK):
      digest.update(chunk)
  return digest.hexdigest()


def _read_manifest(directory: Path) -> dict[str, Any]:
  path = directory / MANIFEST
  if not path.is_file():
    return {}
  try:
    manifest = json.loads(path.read_text())
  except (OSError, ValueError) as e:
    raise CorruptRunError(f"{path}: unreadable checksum manifest ({e})") from e
  if not isinstance(manifest, dict):
    raise CorruptRunError(f"{path}: checksum manifest is not a JSON object")
  return manifest


def _digests(entry: Any) -> list[str]:
  return [entry] if isinstance(entry, str) else list(entry or [])


def _write_manifest(directory: Path, manifest: dict[str, Any]) -> None:
  atomic.write_json(directory / MANIFEST, manifest, indent=1, sort_keys=True)


def write_all(files: dict[str | os.PathLike, bytes]) -> None:
  """Writes {path: bytes} of one existing directory as a group (`atomic.write_all`: all
  new or all old) and records every digest; after a failure the manifest is as before
  (or absent, as before)."""
  paths = [Path(p) for p in files]
  directory = paths[0].parent
  if any(p.parent != directory for p in paths):
    raise ValueError(f"checksums.write_all: files of several directories: {paths}")
  manifest, fresh = _read_manifest(directory), not (directory / MANIFEST).exists()
  before = dict(manifest)
  digests = {p.name: sha256(data) for p, data in zip(paths, files.values())}
  for name, digest in digests.items():
    manifest[name] = sorted({*_digests(manifest.get(name)), digest})
  _write_manifest(directory, manifest)
  try:
    atomic.write_all(files)
  except BaseException:
    if fresh:
      (directory / MANIFEST).unlink()
    else:  # if even this fails, the extra digests are harmless: the old ones are listed
      with contextlib.suppress(OSError):
        _write_manifest(directory, before)
    raise
  manifest.update(digests)
  _write_manifest(directory, manifest)


def write_bytes(path: str | os.PathLike, data: bytes) -> None:
  """Writes `data` atomically to `path` and records its digest; the directory must exist."""
  write_all({path: data})


def read_bytes(path: str | os.PathLike) -> bytes:
  """The bytes of `path`, verified against its recorded digest.

  Raises:
    FileNotFoundError: no such file.
    CorruptRunError: the content differs from the recorded digest.
  """
  path = Path(path)
  data = path.read_bytes()
  entry = _read_manifest(path.parent).get(path.name)
  if entry is None:
    raise CorruptRunError(
        f"{path}: no checksum in {path.parent / MANIFEST} (a file of an "
        "older version, or copied without its manifest); rerun the command "
        "that wrote it"
    )
  if sha256(data) not in _digests(entry):
    raise CorruptRunError(
        f"{path}: content does not match its sha256 in {path.parent / MANIFEST} (the file "
        "is corrupt or was edited); restore it or rerun the command that wrote it"
    )
  return data


def write_json(path: str | os.PathLike, value: Any, **kwargs) -> None:
  """`value` as JSON (indent 2 unless `kwargs` say otherwise), checksummed."""
  write_bytes(path, atomic.json_text(value, **kwargs).encode())


def read_json(path: str | os.PathLike) -> Any:
  """A file of `write_json`, verified; CorruptRunError naming the file if unparseable."""
  data = read_bytes(path)
  try:
    return json.loads(data)
  except ValueError as e:
    raise CorruptRunError(f"{path}: not valid JSON ({e})") from e


def npz_bytes(**arrays) -> bytes:
  """Arrays as the bytes of an uncompressed .npz (`np.savez`), for `write_all`."""
  buffer = io.BytesIO()
  np.savez(buffer, **arrays)
  return buffer.getvalue()


def write_npz(path: str | os.PathLike, **arrays) -> None:
  """Arrays as an uncompressed .npz (`np.savez`), checksummed."""
  write_bytes(path, npz_bytes(**arrays))


def read_npz(path: str | os.PathLike) -> dict[str, np.ndarray]:
  """All arrays of a file of `write_npz`, verified; CorruptRunError if unreadable."""
  data = read_bytes(path)
  try:
    with np.load(io.BytesIO(data), allow_pickle=False) as npz:
      return {name: npz[name] for name in npz.files}
  except (zipfile.BadZipFile, OSError, EOFError, ValueError) as e:
    raise CorruptRunError(f"{path}: unreadable .npz file ({e})") from e


def record_tree(directory: str | os.PathLike) -> None:
  """Writes <directory>/checksums.json with the sha256 of every file below `directory`."""
  directory = Path(directory)
  _write_manifest(directory, _tree_digests(directory))


def _tree_digests(directory: Path) -> dict[str, str]:
  return {
      p.relative_to(directory).as_posix(): file_sha256(p)
      for p in sorted(directory.rglob("*"))
      if p.is_file() and p.name != MANIFEST
  }


def verify_tree(directory: str | os.PathLike) -> None:
  """Raises CorruptRunError naming the files below `directory` that differ from (or are
  missing from, or were added to) its checksums.json."""
  directory = Path(directory)
  if not (directory / MANIFEST).is_file():
    raise CorruptRunError(f"{directory}: no {MANIFEST}; its files cannot be verified")
  saved, now = _read_manifest(directory), _tree_digests(directory)
  bad = sorted(k for k in set(saved) | set(now) if saved.get(k) != now.get(k))
  if bad:
    raise CorruptRunError(
        f"file(s) {bad[:4]} below {directory} differ from their sha256 " f"in its {MANIFEST}"
    )
