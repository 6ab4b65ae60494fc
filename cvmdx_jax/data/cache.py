"""Scenario cache: one float32 .npz per split plus metadata.json, written atomically.

metadata.json = {"format_version", "settings", "sources": [[name, bytes, sha256], ...],
"splits": {name: {"file", "bytes", "sha256", "count"}}}; source names are relative to the
source directory, so the same data under another spelling of its path (relative, absolute,
through a symlink) is the same dataset. It is written last, and each split file's size and
hash are checked on reading, so a cache cut short by a crash or made with other settings or
sources is never taken for a valid one; metadata of any other shape counts as no cache.
The dataset id (`dataset_id`) is a hash of the format version, settings and sources only.
"""

import hashlib
import io
import json
from pathlib import Path

import numpy as np

from cvmdx_jax.storage import atomic
from cvmdx_jax.data import scenarios as scenarios_lib
from cvmdx_jax.data.errors import DataError

FORMAT_VERSION = 2
METADATA = "metadata.json"
_CHUNK = 1 << 20


def file_sha256(path) -> str:
  """Hex sha256 of a file's bytes, read in 1 MiB chunks."""
  digest = hashlib.sha256()
  with open(path, "rb") as handle:
    while chunk := handle.read(_CHUNK):
      digest.update(chunk)
  return digest.hexdigest()


def sources(root, paths) -> list:
  """[[name relative to `root` (posix), bytes, sha256], ...] sorted by name."""
  root = Path(root)
  rows = [[Path(p).relative_to(root).as_posix(), Path(p).stat().st_size, file_sha256(p)]
          for p in paths]
  return sorted(rows)


def write(cache_dir, splits: dict, settings: dict, sources: list) -> dict:
  """Writes every split, then the metadata; returns the metadata."""
  cache_dir = Path(cache_dir)
  cache_dir.mkdir(parents=True, exist_ok=True)
  entries = {}
  for name, scen in splits.items():
    buffer = io.BytesIO()
    np.savez(buffer, **scen.as_dict())
    data = buffer.getvalue()
    atomic.write_bytes(cache_dir / f"{name}.npz", data)
    entries[name] = {"file": f"{name}.npz", "bytes": len(data),
                     "sha256": hashlib.sha256(data).hexdigest(), "count": len(scen)}
  metadata = {"format_version": FORMAT_VERSION, "settings": settings,
              "sources": [list(s) for s in sources], "splits": entries}
  atomic.write_bytes(cache_dir / METADATA, json.dumps(metadata, indent=1, sort_keys=True).encode())
  return metadata


def _is_int(value) -> bool:
  return isinstance(value, int) and not isinstance(value, bool)


def _is_sha256(value) -> bool:
  return (isinstance(value, str) and len(value) == 64
          and all(c in "0123456789abcdef" for c in value))


def _well_formed(metadata) -> bool:
  """True when `metadata` has the shape `write` gives it (types included)."""
  if not (isinstance(metadata, dict) and metadata.get("format_version") == FORMAT_VERSION
          and isinstance(metadata.get("settings"), dict)
          and isinstance(metadata.get("sources"), list)
          and isinstance(metadata.get("splits"), dict)):
    return False
  for source in metadata["sources"]:
    if not (isinstance(source, list) and len(source) == 3 and isinstance(source[0], str)
            and _is_int(source[1]) and _is_sha256(source[2])):
      return False
  for name, entry in metadata["splits"].items():
    if not (name.isidentifier() and isinstance(entry, dict) and entry.get("file") == f"{name}.npz"
            and _is_int(entry.get("bytes")) and _is_sha256(entry.get("sha256"))
            and _is_int(entry.get("count"))):
      return False
  return True


def read_metadata(cache_dir) -> dict | None:
  """The metadata, or None where there is no readable, well-formed cache."""
  try:
    metadata = json.loads((Path(cache_dir) / METADATA).read_text())
  except (OSError, ValueError):
    return None
  return metadata if _well_formed(metadata) else None


def matches(metadata: dict | None, settings: dict, sources: list) -> bool:
  """True when `metadata` was made with these settings from these source files."""
  return (metadata is not None and metadata["settings"] == json.loads(json.dumps(settings))
          and metadata["sources"] == [list(s) for s in sources])


def dataset_id(metadata: dict) -> str:
  """12 hex digits of sha256 over format version, settings and sources (not the paths)."""
  content = {k: metadata[k] for k in ("format_version", "settings", "sources")}
  return hashlib.sha256(json.dumps(content, sort_keys=True).encode()).hexdigest()[:12]


def read_split(cache_dir, split: str) -> scenarios_lib.Scenarios:
  """Reads split `split`; raises DataError if absent, unknown or inconsistent."""
  cache_dir = Path(cache_dir)
  metadata = read_metadata(cache_dir)
  if metadata is None:
    raise DataError(cache_dir / METADATA, "no dataset cache here, or a malformed or older "
                    "one (run make_dataset)")
  entries = metadata["splits"]
  if split not in entries:
    raise DataError(cache_dir / METADATA, f"unknown split '{split}', available: "
                    f"{sorted(entries)}", column="split")
  entry, path = entries[split], cache_dir / entries[split]["file"]
  try:
    data = path.read_bytes()
  except OSError as err:
    raise DataError(path, f"cache file unreadable ({err})") from err
  if len(data) != entry["bytes"] or hashlib.sha256(data).hexdigest() != entry["sha256"]:
    raise DataError(path, "cache file does not match metadata.json (interrupted build?)")
  with np.load(io.BytesIO(data)) as arrays:
    return scenarios_lib.Scenarios(**{k: arrays[k] for k in scenarios_lib.FIELDS}).validate(
        str(path))
