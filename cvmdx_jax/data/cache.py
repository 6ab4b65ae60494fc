"""Scenario cache: one float32 .npz per split plus metadata.json, written atomically and
checksummed (`storage.checksums`, the cache directory's checksums.json).

metadata.json = {"format_version", "settings", "sources": [[name, bytes, sha256], ...],
"splits": {name: {"file", "count"}}}; source names are relative to the source directory,
so the same data under another spelling of its path (relative, absolute, through a
symlink) is the same dataset. It is written last, and each split file is verified against
its checksum on reading, so a cache cut short by a crash or made with other settings or
sources is never taken for a valid one; metadata of any other shape counts as no cache.
The dataset id (`dataset_id`) is the `storage.identity.content_id` of the format version,
settings and sources only.
"""

from pathlib import Path

from cvmdx_jax.data import scenarios as scenarios_lib
from cvmdx_jax.data.errors import DataError
from cvmdx_jax.storage import checksums, identity

FORMAT_VERSION = 2  # a cache of an older layout has no checksums.json: rebuilt
METADATA = "metadata.json"


def sources(root, paths) -> list:
  """[[name relative to `root` (posix), bytes, sha256], ...] sorted by name."""
  root = Path(root)
  rows = [
      [Path(p).relative_to(root).as_posix(), Path(p).stat().st_size, checksums.file_sha256(p)]
      for p in paths
  ]
  return sorted(rows)


def write(cache_dir, splits: dict, settings: dict, sources: list) -> dict:
  """Writes every split, then the metadata; returns the metadata."""
  cache_dir = Path(cache_dir)
  cache_dir.mkdir(parents=True, exist_ok=True)
  entries = {}
  for name, scen in splits.items():
    checksums.write_npz(cache_dir / f"{name}.npz", **scen.as_dict())
    entries[name] = {"file": f"{name}.npz", "count": len(scen)}
  metadata = {
      "format_version": FORMAT_VERSION,
      "settings": settings,
      "sources": [list(s) for s in sources],
      "splits": entries,
  }
  checksums.write_json(cache_dir / METADATA, metadata, indent=1, sort_keys=True)
  return metadata


def _is_int(value) -> bool:
  return isinstance(value, int) and not isinstance(value, bool)


def _well_formed(metadata) -> bool:
  """True when `metadata` has the shape `write` gives it (types included)."""
  if not (
      isinstance(metadata, dict)
      and metadata.get("format_version") == FORMAT_VERSION
      and isinstance(metadata.get("settings"), dict)
      and isinstance(metadata.get("sources"), list)
      and isinstance(metadata.get("splits"), dict)
  ):
    return False
  for source in metadata["sources"]:
    if not (
        isinstance(source, list)
        and len(source) == 3
        and isinstance(source[0], str)
        and _is_int(source[1])
        and isinstance(source[2], str)
    ):
      return False
  for name, entry in metadata["splits"].items():
    if not (
        name.isidentifier()
        and isinstance(entry, dict)
        and entry.get("file") == f"{name}.npz"
        and _is_int(entry.get("count"))
    ):
      return False
  return True


def read_metadata(cache_dir) -> dict | None:
  """The metadata, or None where there is no readable, intact, well-formed cache."""
  try:
    metadata = checksums.read_json(Path(cache_dir) / METADATA)
  except (OSError, ValueError):
    return None
  return metadata if _well_formed(metadata) else None


def required_metadata(cache_dir) -> dict:
  """The metadata of the cache in `cache_dir`; DataError naming its metadata.json where
  there is none (or a malformed or older one)."""
  metadata = read_metadata(cache_dir)
  if metadata is None:
    raise DataError(
        Path(cache_dir) / METADATA,
        "no dataset cache here, or a malformed or " "older one (run make_dataset)",
    )
  return metadata


def matches(metadata: dict | None, settings: dict, sources: list) -> bool:
  """True when `metadata` was made with these settings from these source files."""
  return metadata is not None and not identity.differing_keys(
      {"settings": metadata["settings"], "sources": metadata["sources"]},
      {"settings": settings, "sources": sources},
  )


def dataset_id(metadata: dict) -> str:
  """12 hex digits of the content id of format version, settings and sources (not the
  paths)."""
  return identity.content_id({k: metadata[k] for k in ("format_version", "settings", "sources")})[
      :12
  ]


def read_split(cache_dir, split: str) -> scenarios_lib.Scenarios:
  """Reads split `split`; raises DataError if absent, unknown or inconsistent."""
  cache_dir = Path(cache_dir)
  entries = required_metadata(cache_dir)["splits"]
  if split not in entries:
    raise DataError(
        cache_dir / METADATA,
        f"unknown split '{split}', available: " f"{sorted(entries)}",
        column="split",
    )
  path = cache_dir / entries[split]["file"]
  try:
    arrays = checksums.read_npz(path)
  except OSError as err:
    raise DataError(path, f"cache file unreadable ({err})") from err
  except checksums.CorruptRunError as err:
    raise DataError(
        path, f"cache file does not match its checksum (interrupted build?): " f"{err}"
    ) from err
  return scenarios_lib.Scenarios(**{k: arrays[k] for k in scenarios_lib.FIELDS}).validate(str(path))
