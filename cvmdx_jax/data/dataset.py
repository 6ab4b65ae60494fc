"""Build, cache and load the dataset splits for one of three sources.

Sources (`config.source`): 'sumo' (simulate the recordings of `config.sumo.recordings` into
`data_dir/recordings`, highD format, then read them like highD), 'highd' (`config.highd_dir`),
'cvmd_mat' (`config.mat_dir/{train,test}`). Splits (`SPLITS`), disjoint by recording: sumo
by `sumo_plan.split_ids`, highd by the recording ids of `config.splits` (a split given no ids
is not built, so that recordings of a road never seen can make a test-only dataset for a
trained model; at least one split must hold a recording), cvmd_mat: test = `test/`, val = a seeded,
per-class `config.mat_val_fraction` of the `train/` files, train = the rest.
The cache lives in `data_dir/cache` (see `cache`); it is reused only when it was made with the
same settings from source files of the same content (names relative to the source directory,
sizes, sha256), otherwise rebuilt. `dataset_id` hashes exactly these, so it does not depend on
how `data_dir`, `highd_dir` or `mat_dir` is spelled.
"""

import json
from pathlib import Path

import numpy as np

from cvmdx_jax.config.fields import (
    BELOW_ONE,
    FRACTION,
    NON_NEGATIVE,
    POSITIVE,
    SEED,
    ConfigFieldError,
    check_ranges,
)
from cvmdx_jax.data import cache, cvmd_mat, extract, highd, sumo, sumo_plan
from cvmdx_jax.data import scenarios as scenarios_lib
from cvmdx_jax.data.errors import DataError
from cvmdx_jax.storage import atomic, identity, locking

SOURCES = ("sumo", "highd", "cvmd_mat")
SPLITS = sumo_plan.SPLITS  # train, val, test, test_ood, val_ood
_MAT_SPLITS = ("train", "val", "test")  # what a cvmd_mat source builds
# Ranges of the numeric fields of configs/dataset.py per section (a tuple: each element).
CONFIG_RANGES = {
    "": {"seed": SEED, "mat_val_fraction": BELOW_ONE},
    "splits": dict.fromkeys(SPLITS, POSITIVE),
    "extraction": {
        "seed": SEED,
        "lc_offsets_s": POSITIVE,
        "kl_stride_s": POSITIVE,
        "control_smoothing": NON_NEGATIVE,
        "control_iterations": POSITIVE,
    },
    "sumo": {
        "seed": SEED,
        "warmup_s": NON_NEGATIVE,
        "truck_share": FRACTION,
        **dict.fromkeys(
            (
                "workers",
                "duration_s",
                "road_length_m",
                "section_length_m",
                "lanes",
                "lane_width_m",
                "speed_limits_kmh",
                "flow_per_lane",
                "car_types",
                "truck_types",
            ),
            POSITIVE,
        ),
    },
    "sumo.recordings": dict.fromkeys(SPLITS, NON_NEGATIVE),
    "sumo.held_out": {"lanes": POSITIVE, "duration_s": POSITIVE},
    "sumo.val_held_out": {"lanes": POSITIVE, "duration_s": POSITIVE},
}


def checked_config(config):
  """`config` (configs/dataset.py) once every numeric field is in its range
  (`CONFIG_RANGES`); ConfigFieldError naming the dotted field otherwise."""
  for section, ranges in CONFIG_RANGES.items():
    node = config
    for part in section.split(".") if section else ():
      node = node[part]
    try:
      check_ranges(node, ranges)
    except ConfigFieldError as e:
      raise (e.within(section) if section else e) from None
  return config


def _settings(config) -> dict:
  """The config fields that determine the data: worker count, unused sources and the source
  directories dropped (the sources' content stands for them, see `cache.sources`)."""
  c = config.to_dict()
  c["sumo"].pop("workers", None)
  if c["source"] != "sumo":
    c.pop("sumo")
  c.pop("highd_dir", None)
  c.pop("mat_dir", None)
  return identity.to_json(c, "dataset settings")


def _wanted_ids(config, data_dir: Path) -> dict:
  """{split: recording ids asked for} (SUMO: numbered by `sumo_plan.split_ids`); DataError,
  before anything is simulated or read, where no split has one. A split given no ids
  (highD: `()`, SUMO: 0 recordings) is not built."""
  sumo_source = config.source == "sumo"
  wanted = (
      sumo_plan.split_ids(config.sumo)
      if sumo_source
      else {name: list(config.splits.get(name, ())) for name in SPLITS}
  )
  if not any(wanted.values()):
    raise DataError(
        data_dir,
        "empty selection: no split has a recording",
        column="sumo.recordings" if sumo_source else "splits",
    )
  return wanted


def _sumo_recordings(config, data_dir: Path, wanted: dict) -> Path:
  """data_dir/recordings, simulated unless a stamp says they were made with these settings."""
  rec_dir = data_dir / "recordings"
  stamp = rec_dir / "sumo_settings.json"
  settings = json.dumps(_settings(config)["sumo"], sort_keys=True)
  ids = [i for split in wanted.values() for i in split]
  present = all(p.is_file() for i in ids for p in highd.recording_paths(rec_dir, i).values())
  if not (present and stamp.is_file() and stamp.read_text() == settings):
    stamp.unlink(missing_ok=True)
    sumo.make_recordings(config.sumo, rec_dir)
    atomic.write_text(stamp, settings)
  return rec_dir


def _split_ids(config, wanted: dict, available, where) -> dict:
  """{split: recording ids of `wanted` present}; DataError for a split whose ids are all
  missing, or for a recording in two splits."""
  column = "sumo.recordings" if config.source == "sumo" else "splits"
  out, seen = {}, {}
  for name in SPLITS:
    for i in wanted[name]:
      if i in seen:
        raise DataError(
            where, f"recording {i} is in both {seen[i]} and {name}", column=f"{column}.{name}"
        )
      seen[i] = name
    ids = [i for i in wanted[name] if i in available]
    if not ids and wanted[name]:
      hint = (
          ""
          if config.source == "sumo"
          else f"; to build without {name}, give it no ids: --config.splits.{name}=()"
      )
      raise DataError(
          where,
          f"empty selection: none of the {name} recordings "
          f"{wanted[name]} is there (have {available}){hint}",
          column=f"{column}.{name}",
      )
    if ids:
      out[name] = ids
  return out


def mat_val_index(labels, fraction: float, seed: int) -> np.ndarray:
  """Sorted indices of the val scenarios carved from cvmd_mat train: per class
  round(fraction * count) drawn with `np.random.default_rng([seed, class])`."""
  labels = np.asarray(labels)
  picks = []
  for c in np.unique(labels):
    members = np.flatnonzero(labels == c)
    count = int(round(fraction * len(members)))
    picks.append(np.random.default_rng([seed, int(c)]).choice(members, count, replace=False))
  return np.sort(np.concatenate(picks)) if picks else np.zeros((0,), np.int64)


def _read_mat(config, mat_dir: Path) -> dict:
  train = cvmd_mat.load(mat_dir / "train")
  val = mat_val_index(train.label, config.mat_val_fraction, config.seed)
  if len(val) == 0 or len(val) == len(train):
    raise DataError(
        mat_dir / "train",
        f"mat_val_fraction {config.mat_val_fraction} leaves "
        f"train or val empty ({len(train)} files)",
        column="mat_val_fraction",
    )
  return {
      "train": train.take(np.setdiff1d(np.arange(len(train)), val)),
      "val": train.take(val),
      "test": cvmd_mat.load(mat_dir / "test"),
  }


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
  checked_config(config)
  if config.source not in SOURCES:
    raise DataError(
        data_dir,
        f"unknown source '{config.source}', expected one of {SOURCES}",
        column="config.source",
    )
  settings = _settings(config)
  if config.source == "cvmd_mat":
    mat_dir = root = Path(config.mat_dir)
    files = list(mat_dir.glob("*/class*/*.mat"))
    names = _MAT_SPLITS
    read = lambda: _read_mat(config, mat_dir)
  else:
    wanted = _wanted_ids(config, data_dir)
    rec_dir = root = (
        _sumo_recordings(config, data_dir, wanted)
        if config.source == "sumo"
        else Path(config.highd_dir)
    )
    if not rec_dir.is_dir():
      raise DataError(rec_dir, "highD directory not found", column="config.highd_dir")
    ids = _split_ids(config, wanted, highd.available_recordings(rec_dir), rec_dir)
    files = [
        p
        for split in ids.values()
        for i in split
        for p in highd.recording_paths(rec_dir, i).values()
        if p.is_file()
    ]
    ext = extract.as_config(config.extraction)
    names = tuple(ids)
    read = lambda: {name: highd.load_scenarios(rec_dir, ids[name], ext) for name in names}
  sources = cache.sources(root, files)
  cache_dir = data_dir / "cache"
  if cache.matches(cache.read_metadata(cache_dir), settings, sources):
    try:
      return {name: cache.read_split(cache_dir, name) for name in names}
    except DataError:
      pass  # inconsistent cache: rebuild below
  splits = read()
  cache.write(cache_dir, splits, settings, sources)
  return splits


def load_split(data_dir, split: str):
  """The cached split `split` written by `build` (DataError lists the available ones)."""
  return cache.read_split(Path(data_dir) / "cache", split)


def load_balanced(data_dir, split: str, seed: int = 0, size: int = 0):
  """`load_split`, then a class-balanced subset of `size` scenarios drawn with `seed`
  (`scenarios.balanced_indices`); `size` 0: the whole split."""
  scenarios = load_split(data_dir, split)
  if size:
    scenarios = scenarios.take(scenarios_lib.balanced_indices(scenarios.label, seed, size))
  return scenarios


def dataset_id(data_dir) -> str:
  """12 hex digits: content hash of the cached dataset's settings and sources (`cache`)."""
  return cache.dataset_id(cache.required_metadata(Path(data_dir) / "cache"))


def split_names(data_dir) -> list:
  """Names of the cached splits in `data_dir`, in `SPLITS` order (others after, sorted)."""
  names = cache.required_metadata(Path(data_dir) / "cache").get("splits", {})
  return [s for s in SPLITS if s in names] + sorted(set(names) - set(SPLITS))
