"""Scenario cache: one float32 .npz per split plus metadata.json, written atomically.

metadata.json = {"format_version", "settings", "sources": [[path, bytes], ...],
"splits": {name: {"file", "bytes", "sha256", "count"}}}. It is written last, and each split
file's size and hash are checked on reading, so a cache cut short by a crash or made with
other settings or sources is never taken for a valid one.
"""

import hashlib
import io
import json
from pathlib import Path

import numpy as np

from cvmdx_jax import atomic
from cvmdx_jax.data import scenarios as scenarios_lib
from cvmdx_jax.data.errors import DataError

FORMAT_VERSION = 1
METADATA = "metadata.json"


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


def read_metadata(cache_dir) -> dict | None:
  """The metadata, or None where there is no readable cache."""
  try:
    return json.loads((Path(cache_dir) / METADATA).read_text())
  except (OSError, ValueError):
    return None


def matches(metadata: dict | None, settings: dict, sources: list) -> bool:
  """True when `metadata` was made with these settings from these source files."""
  return (metadata is not None and metadata.get("format_version") == FORMAT_VERSION
          and metadata.get("settings") == json.loads(json.dumps(settings))
          and metadata.get("sources") == [list(s) for s in sources])


def read_split(cache_dir, split: str) -> scenarios_lib.Scenarios:
  """Reads split `split`; raises DataError if absent, unknown or inconsistent."""
  cache_dir = Path(cache_dir)
  metadata = read_metadata(cache_dir)
  if metadata is None:
    raise DataError(cache_dir / METADATA, "no dataset cache here (run make_dataset)")
  entries = metadata.get("splits", {})
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
