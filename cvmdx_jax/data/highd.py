"""Raw highD recordings: read, validate, move to a road-aligned frame; `load_scenarios`.

A recording XX is three CSV files in one directory: XX_tracks.csv (one row per vehicle and
frame), XX_tracksMeta.csv (one row per vehicle), XX_recordingMeta.csv (one row). Raw
coordinates are image-style: x to the right, y down, (x, y) the upper-left corner of the
bounding box, `width` the vehicle length and `height` its width; drivingDirection 1 drives
toward -x (upper lanes), 2 toward +x (lower lanes).

Road frame per direction (right-handed, x along travel, y to the driver's left), applied to
the bounding-box centre and to velocities: direction 2: (x, -y); direction 1: (-x, y).

Errors name the file, the 1-based line (the header is line 1) and the column.
"""

import dataclasses
from pathlib import Path

import numpy as np
import pandas as pd

from cvmdx_jax import constants
from cvmdx_jax.data import extract
from cvmdx_jax.data import scenarios as scenarios_lib
from cvmdx_jax.data.errors import DataError

TRACKS_COLUMNS = (
    "frame", "id", "x", "y", "width", "height", "xVelocity", "yVelocity", "xAcceleration",
    "yAcceleration", "frontSightDistance", "backSightDistance", "dhw", "thw", "ttc",
    "precedingXVelocity", "precedingId", "followingId", "leftPrecedingId", "leftAlongsideId",
    "leftFollowingId", "rightPrecedingId", "rightAlongsideId", "rightFollowingId", "laneId")
TRACKS_META_COLUMNS = (
    "id", "width", "height", "initialFrame", "finalFrame", "numFrames", "class",
    "drivingDirection", "traveledDistance", "minXVelocity", "maxXVelocity", "meanXVelocity",
    "minDHW", "minTHW", "minTTC", "numLaneChanges")
RECORDING_META_COLUMNS = (
    "id", "frameRate", "locationId", "speedLimit", "month", "weekDay", "startTime", "duration",
    "totalDrivenDistance", "totalDrivenTime", "numVehicles", "numCars", "numTrucks",
    "upperLaneMarkings", "lowerLaneMarkings")
_TEXT_COLUMNS = ("class", "month", "weekDay", "startTime", "upperLaneMarkings",
                 "lowerLaneMarkings")
# Neighbour columns in `constants.VEHICLE_SLOTS[1:]` order.
NEIGHBOUR_COLUMNS = tuple(f"{slot}Id" for slot in constants.VEHICLE_SLOTS[1:])


def recording_paths(data_dir, recording_id: int) -> dict:
  """{'tracks', 'tracksMeta', 'recordingMeta'} -> Path of recording `recording_id`."""
  base = Path(data_dir)
  return {kind: base / f"{recording_id:02d}_{kind}.csv"
          for kind in ("tracks", "tracksMeta", "recordingMeta")}


def _read_table(path: Path, columns) -> pd.DataFrame:
  """Reads one CSV and checks its header, numeric cells and NaNs."""
  if not path.is_file():
    raise DataError(path, "file not found")
  try:
    frame = pd.read_csv(path, skipinitialspace=True)
  except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as err:
    raise DataError(path, f"unreadable CSV ({str(err).strip()})") from err
  header = list(frame.columns)
  for name in columns:
    if name not in header:
      raise DataError(path, f"missing column (header has {header})", row=1, column=name)
  if len(frame) == 0:
    raise DataError(path, "no data rows", row=2)
  for name in columns:
    values = frame[name]
    if name in _TEXT_COLUMNS:
      bad = values.isna().to_numpy()
    else:
      if not pd.api.types.is_numeric_dtype(values):
        values = pd.to_numeric(values, errors="coerce")
        bad = values.isna().to_numpy() & frame[name].notna().to_numpy()
        if bad.any():
          row = int(np.argmax(bad))
          raise DataError(path, f"non-numeric value {frame[name].iloc[row]!r}",
                          row=row + 2, column=name)
        frame[name] = values
      bad = ~np.isfinite(values.to_numpy(np.float64))
    if bad.any():
      row = int(np.argmax(bad))
      raise DataError(path, "empty, NaN or infinite value (truncated file?)",
                      row=row + 2, column=name)
  return frame


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
  rec_meta = _read_table(paths["recordingMeta"], RECORDING_META_COLUMNS)
  if int(rec_meta["frameRate"].iloc[0]) != constants.FRAME_RATE_HZ:
    raise DataError(paths["recordingMeta"], f"frame rate {rec_meta['frameRate'].iloc[0]}, "
                    f"expected {constants.FRAME_RATE_HZ}", row=2, column="frameRate")
  meta = _read_table(paths["tracksMeta"], TRACKS_META_COLUMNS)
  tracks = _read_table(paths["tracks"], TRACKS_COLUMNS)
  meta_path, path = paths["tracksMeta"], paths["tracks"]

  meta_ids = meta["id"].to_numpy(np.int64)
  if meta_ids.min() < 1 or len(np.unique(meta_ids)) != len(meta_ids):
    raise DataError(meta_path, "track ids must be unique and >= 1", column="id")
  direction_of = meta["drivingDirection"].to_numpy(np.int64)
  bad = ~np.isin(direction_of, (1, 2))
  if bad.any():
    raise DataError(meta_path, "drivingDirection must be 1 or 2",
                    row=int(np.argmax(bad)) + 2, column="drivingDirection")
  size = meta_ids.max() + 1
  known = np.zeros(size + 1, bool)
  known[meta_ids] = True

  ids = tracks["id"].to_numpy(np.int64)
  frames = tracks["frame"].to_numpy(np.int64)
  for column in ("id", *NEIGHBOUR_COLUMNS):
    values = tracks[column].to_numpy(np.int64)
    bad = (values != 0) | (column == "id")
    bad &= ~known[np.clip(values, 0, size)]
    if bad.any():
      row = int(np.argmax(bad))
      raise DataError(path, f"track id {values[row]} does not exist in {meta_path.name}",
                      row=row + 2, column=column)
  # Rows must be grouped by track with consecutive frames from the track's initialFrame.
  meta_first = np.zeros(size, np.int64)
  meta_first[meta_ids] = meta["initialFrame"].to_numpy(np.int64)
  meta_num = np.zeros(size, np.int64)
  meta_num[meta_ids] = meta["numFrames"].to_numpy(np.int64)
  starts = np.flatnonzero(np.r_[True, ids[1:] != ids[:-1]])
  first_row = np.zeros(size, np.int64)
  first_row[ids[starts]] = starts
  expected = meta_first[ids] + np.arange(len(ids)) - first_row[ids]
  bad = frames != expected
  bad[starts] |= np.bincount(ids[starts], minlength=size)[ids[starts]] > 1
  if bad.any():
    row = int(np.argmax(bad))
    raise DataError(path, f"frames of track {ids[row]} are not consecutive from its "
                    f"initialFrame {meta_first[ids[row]]} (rows sorted by id, then frame)",
                    row=row + 2, column="frame")
  first_frame = meta_first
  num_frames = np.zeros(size, np.int64)
  num_frames[ids[starts]] = np.diff(np.r_[starts, len(ids)])
  bad = num_frames[meta_ids] != meta_num[meta_ids]
  if bad.any():
    row = int(np.argmax(bad))
    raise DataError(meta_path, f"track {meta_ids[row]} has {num_frames[meta_ids[row]]} rows "
                    f"in {path.name} (truncated?)", row=row + 2, column="numFrames")

  dir_by_id = np.zeros(size, np.int64)
  dir_by_id[meta_ids] = direction_of
  direction = dir_by_id[ids]
  sign = np.where(direction == 2, 1.0, -1.0)
  col = lambda name: tracks[name].to_numpy(np.float64)
  centre_x = col("x") + 0.5 * col("width")
  centre_y = col("y") + 0.5 * col("height")
  pos = np.stack([sign * centre_x, -sign * centre_y], -1)
  vel = np.stack([sign * col("xVelocity"), -sign * col("yVelocity")], -1)
  neighbours = np.stack([tracks[c].to_numpy(np.int64) for c in NEIGHBOUR_COLUMNS], -1)
  return Recording(recording_id=recording_id, path=str(path), track_id=ids, frame=frames,
                   lane=tracks["laneId"].to_numpy(np.int64), direction=direction, pos=pos,
                   vel=vel, neighbours=neighbours, first_row=first_row,
                   first_frame=first_frame, num_frames=num_frames)


def available_recordings(data_dir) -> list[int]:
  """Ids XX of the XX_tracks.csv files in `data_dir`, sorted."""
  ids = []
  for path in Path(data_dir).glob("*_tracks.csv"):
    stem = path.name[: -len("_tracks.csv")]
    if stem.isdigit():
      ids.append(int(stem))
  return sorted(ids)


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
      (read_recording(data_dir, rid) for rid in recording_ids), config, source=str(data_dir))
