"""Build, cache and load the dataset splits for one of three sources.

Sources (`config.source`): 'sumo' (simulate `config.sumo.num_recordings` recordings into
`data_dir/recordings`, highD format, then read them like highD), 'highd' (`config.highd_dir`),
'cvmd_mat' (`config.mat_dir/{train,test}`). Splits by recording id from `config.splits`.
The cache lives in `data_dir/cache` (see `cache`); it is reused only when it was made with the
same settings from source files of the same content (names relative to the source directory,
sizes, sha256), otherwise rebuilt. `dataset_id` hashes exactly these, so it does not depend on
how `data_dir`, `highd_dir` or `mat_dir` is spelled.
"""

import json
from pathlib import Path

from cvmdx_jax import atomic, locking
from cvmdx_jax.data import cache, cvmd_mat, extract, highd, sumo
from cvmdx_jax.data.errors import DataError

SOURCES = ("sumo", "highd", "cvmd_mat")


def _settings(config) -> dict:
  """The config fields that determine the data: worker count, unused sources and the source
  directories dropped (the sources' content stands for them, see `cache.sources`)."""
  c = config.to_dict()
  c["sumo"].pop("workers", None)
  if c["source"] != "sumo":
    c.pop("sumo")
  c.pop("highd_dir", None)
  c.pop("mat_dir", None)
  return json.loads(json.dumps(c))


def _sumo_recordings(config, data_dir: Path) -> Path:
  """data_dir/recordings, simulated unless a stamp says they were made with these settings."""
  rec_dir = data_dir / "recordings"
  stamp = rec_dir / "sumo_settings.json"
  wanted = json.dumps(_settings(config)["sumo"], sort_keys=True)
  ids = range(1, config.sumo.num_recordings + 1)
  present = all(p.is_file() for i in ids for p in highd.recording_paths(rec_dir, i).values())
  if not (present and stamp.is_file() and stamp.read_text() == wanted):
    stamp.unlink(missing_ok=True)
    sumo.make_recordings(config.sumo, rec_dir)
    atomic.write_text(stamp, wanted)
  return rec_dir


def _split_ids(config, available, where) -> dict:
  out = {}
  for name in ("train", "test"):
    ids = [i for i in getattr(config.splits, name) if i in available]
    if not ids:
      raise DataError(where, f"empty selection: none of the {name} recordings "
                      f"{list(getattr(config.splits, name))} is there (have {available})",
                      column=f"splits.{name}")
    out[name] = ids
  return out


@locking.holds("data_dir")
def build(config, data_dir) -> dict:
  """Builds (or reuses) the cached splits.

  Args:
    config: `configs/dataset.py` ConfigDict.
    data_dir: output directory (cache in data_dir/cache; SUMO recordings in
      data_dir/recordings).

  Returns:
    {split name: Scenarios}. Raises DataError on bad input; the existing cache is then left
    as it was.
  """
  data_dir = Path(data_dir)
  if config.source not in SOURCES:
    raise DataError(data_dir, f"unknown source '{config.source}', expected one of {SOURCES}",
                    column="config.source")
  settings = _settings(config)
  if config.source == "cvmd_mat":
    mat_dir = root = Path(config.mat_dir)
    files = list(mat_dir.glob("*/class*/*.mat"))
    readers = {name: (lambda name=name: cvmd_mat.load(mat_dir / name))
               for name in ("train", "test")}
  else:
    rec_dir = root = (_sumo_recordings(config, data_dir) if config.source == "sumo"
                      else Path(config.highd_dir))
    if not rec_dir.is_dir():
      raise DataError(rec_dir, "highD directory not found", column="config.highd_dir")
    ids = _split_ids(config, highd.available_recordings(rec_dir), rec_dir)
    files = [p for i in ids["train"] + ids["test"]
             for p in highd.recording_paths(rec_dir, i).values() if p.is_file()]
    ext = extract.as_config(config.extraction)
    readers = {name: (lambda name=name: highd.load_scenarios(rec_dir, ids[name], ext))
               for name in ids}
  sources = cache.sources(root, files)
  cache_dir = data_dir / "cache"
  if cache.matches(cache.read_metadata(cache_dir), settings, sources):
    try:
      return {name: cache.read_split(cache_dir, name) for name in readers}
    except DataError:
      pass  # inconsistent cache: rebuild below
  splits = {name: read() for name, read in readers.items()}
  cache.write(cache_dir, splits, settings, sources)
  return splits


def load_split(data_dir, split: str):
  """The cached split `split` written by `build` (DataError lists the available ones)."""
  return cache.read_split(Path(data_dir) / "cache", split)


def dataset_id(data_dir) -> str:
  """12 hex digits: content hash of the cached dataset's settings and sources (`cache`)."""
  metadata = cache.read_metadata(Path(data_dir) / "cache")
  if metadata is None:
    raise DataError(Path(data_dir) / "cache" / cache.METADATA,
                    "no dataset cache here, or a malformed or older one (run make_dataset)")
  return cache.dataset_id(metadata)
