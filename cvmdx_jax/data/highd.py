"""Raw highD recordings: read, validate, move to a road-aligned frame; `load_scenarios`.

A recording XX is three CSV files in one directory: XX_tracks.csv (one row per vehicle and
frame), XX_tracksMeta.csv (one row per vehicle), XX_recordingMeta.csv (one row). XX is the
recording id in decimal digits, with any number of leading zeros (highD writes two, `01`;
`1_` and `002_` name recordings 1 and 2); the three files of a recording share the prefix
of its tracks file, and two tracks files of one id (`1_` and `01_`) are refused. Raw
coordinates are image-style: x to the right, y down, (x, y) the upper-left corner of the
bounding box, `width` the vehicle length and `height` its width; drivingDirection 1 drives
toward -x (upper lanes), 2 toward +x (lower lanes).

Road frame per direction (right-handed, x along travel, y to the driver's left), applied to
the bounding-box centre and to velocities: direction 2: (x, -y); direction 1: (-x, y).

Columns the pipeline reads (`READ_COLUMNS`) are checked strictly (the ranges as each file
is read, the relations between columns and files in `data.highd_checks`): a `DataError`
names the first row outside these ranges (`RANGES`):
- every numeric cell finite and within +-1e9 (catches 1e30 / 1e40 anywhere);
- integer columns (frame, ids, laneId, frame counts, drivingDirection, frameRate) hold
  whole numbers: frame, initialFrame, finalFrame in [0, 1e7]; id in [1, 1e6], neighbour
  ids in [0, 1e6]; laneId in [1, 100]; numFrames in [1, 1e7];
- tracks: x, y within +-1e4 m; width (vehicle length) in (0, 50] m, height (vehicle
  width) in (0, 10] m; |xVelocity| <= 100 m/s, |yVelocity| <= 20 m/s;
- drivingDirection agrees with the x-motion: xVelocity * (+1 for direction 2, -1 for 1)
  >= -1 m/s (a standing vehicle may jitter by rounding), and between consecutive frames of
  a track the centre moves by the mean of the two xVelocity values times 1/25 s within 1 m
  in x, and by at most 20 m/s / 25 Hz = 0.8 m in y;
- tracksMeta finalFrame = initialFrame + numFrames - 1;
- recordingMeta frameRate = 25 and lane markings: ";"-separated finite numbers within
  +-1e4 m, at least two per list, strictly ascending.
Every other column (accelerations, sight distances, dhw, thw, ttc, preceding velocity,
tracksMeta sizes and statistics, the other recordingMeta fields) is not read: an empty,
non-numeric, non-finite or out-of-range cell there (|value| > 1e9; accelerations beyond
+-20 m/s^2, tracksMeta sizes outside the tracks ranges) is a `DataWarning` naming the file,
the first such row and the column, one per column, and the recording is read.

Errors name the file, the 1-based line (the header is line 1) and the column (none for a
missing or empty file, or a line with more fields than the header). A blank line inside a
file is an error at its line; trailing blank lines are ignored. Each file is read in
bounded memory (`data.highd_csv`): a file, line or row count beyond highD's, a binary file
or a line with more fields than the header is refused before it is parsed.
"""

import dataclasses
import re
from pathlib import Path

import numpy as np

from cvmdx_jax.data import extract, highd_checks
from cvmdx_jax.data import scenarios as scenarios_lib
from cvmdx_jax.data.errors import DataError
from cvmdx_jax.data.highd_csv import read_table
from cvmdx_jax.data.highd_format import (  # the format's names, read here and by users
    ABSURD,
    COLUMNS,
    NEIGHBOUR_COLUMNS,
    RANGES,
    READ_COLUMNS,
    RECORDING_META_COLUMNS,
    TRACKS_COLUMNS,
    TRACKS_META_COLUMNS,
)


def recordings_dir(data_dir) -> Path:
  """The folder of the recordings: `data_dir`, or its `data/` subfolder where only that one
  holds *_tracks.csv files (the official download's layout, highD-dataset-v1.0/data/)."""
  base = Path(data_dir)
  if not any(base.glob("*_tracks.csv")) and any((base / "data").glob("*_tracks.csv")):
    return base / "data"
  return base


def _tracks_files(data_dir) -> dict:
  """{recording id: [names of its tracks files]} of the *_tracks.csv files in `data_dir`
  whose prefix is decimal digits ('01_tracks.csv', '1_tracks.csv' -> 1)."""
  found = {}
  for path in sorted(Path(data_dir).glob("*_tracks.csv")):
    stem = path.name[: -len("_tracks.csv")]
    if re.fullmatch(r"[0-9]+", stem):
      found.setdefault(int(stem), []).append(path.name)
  return found


def recording_paths(data_dir, recording_id: int) -> dict:
  """{'tracks', 'tracksMeta', 'recordingMeta'} -> Path of recording `recording_id`: the
  prefix of its tracks file in `data_dir` ('1_', '01_', '002_'), two digits when there is
  none (also the names a writer uses); DataError when two tracks files have this id.
  `data_dir` may also be the folder above `data/` (`recordings_dir`)."""
  base = recordings_dir(data_dir)
  names = _tracks_files(base).get(recording_id, [f"{recording_id:02d}_tracks.csv"])
  if len(names) > 1:
    raise DataError(
        base / names[0],
        f"recording {recording_id} has {len(names)} tracks "
        f"files ({', '.join(names)}); keep one",
    )
  prefix = names[0][: -len("tracks.csv")]
  return {kind: base / f"{prefix}{kind}.csv" for kind in ("tracks", "tracksMeta", "recordingMeta")}


@dataclasses.dataclass(frozen=True)
class Recording:
  """One validated recording, rows sorted by (track id, frame).

  Attributes:
    recording_id: the XX of the file names.
    path: the tracks file (for error messages).
    track_id, frame, lane, direction: (R,) int per row.
    pos: (R, 2) bounding-box centre [s, d] in the road frame of the row's direction, m.
    vel: (R, 2) velocity in the same frame, m/s.
    neighbours: (R, 8) neighbour track ids in slot order, 0 = none.
    first_row, first_frame, num_frames: (max_id + 1,) per track id (num_frames 0 = no track).
  """

  recording_id: int
  path: str
  track_id: np.ndarray
  frame: np.ndarray
  lane: np.ndarray
  direction: np.ndarray
  pos: np.ndarray
  vel: np.ndarray
  neighbours: np.ndarray
  first_row: np.ndarray
  first_frame: np.ndarray
  num_frames: np.ndarray


def read_recording(data_dir, recording_id: int) -> Recording:
  """Reads and validates recording `recording_id` of `data_dir`; raises DataError."""
  paths = recording_paths(data_dir, recording_id)
  rec_meta = read_table(paths["recordingMeta"], "recordingMeta")
  highd_checks.check_recording_meta(paths["recordingMeta"], rec_meta)
  meta = read_table(paths["tracksMeta"], "tracksMeta")
  tracks = read_table(paths["tracks"], "tracks")
  meta_path, path = paths["tracksMeta"], paths["tracks"]
  highd_checks.check_tracks_meta(meta_path, meta)
  meta_ids = meta["id"].to_numpy(np.int64)
  highd_checks.check_track_ids(path, meta_path, tracks, meta_ids)
  ids = tracks["id"].to_numpy(np.int64)
  frames = tracks["frame"].to_numpy(np.int64)
  first_row, first_frame, num_frames = highd_checks.track_rows(path, meta_path, meta, ids, frames)
  dir_by_id = np.zeros(meta_ids.max() + 1, np.int64)
  dir_by_id[meta_ids] = meta["drivingDirection"].to_numpy(np.int64)  # 1 or 2 (RANGES)
  direction = dir_by_id[ids]
  highd_checks.check_motion(path, tracks, direction, ids[1:] == ids[:-1])
  sign = np.where(direction == 2, 1.0, -1.0)
  col = lambda name: tracks[name].to_numpy(np.float64)
  centre_x = col("x") + 0.5 * col("width")
  centre_y = col("y") + 0.5 * col("height")
  pos = np.stack([sign * centre_x, -sign * centre_y], -1)
  vel = np.stack([sign * col("xVelocity"), -sign * col("yVelocity")], -1)
  neighbours = np.stack([tracks[c].to_numpy(np.int64) for c in NEIGHBOUR_COLUMNS], -1)
  return Recording(
      recording_id=recording_id,
      path=str(path),
      track_id=ids,
      frame=frames,
      lane=tracks["laneId"].to_numpy(np.int64),
      direction=direction,
      pos=pos,
      vel=vel,
      neighbours=neighbours,
      first_row=first_row,
      first_frame=first_frame,
      num_frames=num_frames,
  )


def available_recordings(data_dir) -> list[int]:
  """Ids of the recordings in `data_dir` (its *_tracks.csv files, see `recording_paths`),
  sorted."""
  return sorted(_tracks_files(recordings_dir(data_dir)))


def load_scenarios(data_dir, recording_ids, config=None) -> scenarios_lib.Scenarios:
  """Scenarios of the given highD-format recordings (extraction per `extract`).

  Args:
    data_dir: directory holding XX_tracks.csv, XX_tracksMeta.csv, XX_recordingMeta.csv.
    recording_ids: the XX to read.
    config: extraction settings (`configs/dataset.py` `extraction` section); None = defaults.

  Returns:
    `Scenarios`, class-balanced when `config.balance` is set.

  Raises:
    DataError: bad or missing files, or nothing selected.
  """
  recording_ids = list(recording_ids)
  if not recording_ids:
    raise DataError(data_dir, "empty selection: no recording ids given", column="recording_ids")
  config = extract.default_config() if config is None else config
  return extract.scenarios_from_recordings(
      (read_recording(data_dir, rid) for rid in recording_ids), config, source=str(data_dir)
  )
