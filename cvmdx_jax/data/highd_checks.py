"""The checks of a highD recording's tables beyond each column's range (`data.highd`'s
docstring lists them): frame rate and lane markings, tracksMeta's frame counts and ids,
tracks' ids and consecutive frames, drivingDirection against xVelocity and positions
against velocities. Each refusal is a `DataError` naming the file, line and column."""

from pathlib import Path

import numpy as np
import pandas as pd

from cvmdx_jax import constants
from cvmdx_jax.data.errors import DataError
from cvmdx_jax.data.highd_format import NEIGHBOUR_COLUMNS, POSITION

MAX_DIRECTION_SLACK = 1.0  # m/s of xVelocity against the driving direction
MAX_MOTION_MISMATCH = 1.0  # m per frame between x motion and xVelocity * dt
MAX_LATERAL_STEP = 20.0 * constants.DT  # m per frame in y


def refuse_first(path: Path, bad: np.ndarray, column: str, message) -> None:
  """DataError at the first data row i where `bad` (one bool per data row) holds, naming
  its line (i + 2: the header is line 1), `column` and `message(i)`."""
  if bad.any():
    row = int(np.argmax(bad))
    raise DataError(path, message(row), row=row + 2, column=column)


def lane_markings(path: Path, text: str, column: str) -> np.ndarray:
  """Parses '8.51;12.59;16.43' (>= 2 finite ascending values within +-1e4 m)."""
  try:
    values = np.array([float(v) for v in str(text).split(";")])
  except ValueError:
    values = np.array([np.nan])
  if (
      len(values) < 2
      or not np.all(np.isfinite(values))
      or np.any(np.abs(values) > POSITION[1])
      or np.any(np.diff(values) <= 0)
  ):
    raise DataError(
        path,
        f"lane markings {text!r} are not >= 2 ascending numbers " "separated by ';'",
        row=2,
        column=column,
    )
  return values


def check_motion(
    path: Path, tracks: pd.DataFrame, direction: np.ndarray, same_track: np.ndarray
) -> None:
  """drivingDirection against xVelocity, and positions against velocities (docstring)."""
  vx = tracks["xVelocity"].to_numpy(np.float64)
  bad = np.where(direction == 2, vx, -vx) < -MAX_DIRECTION_SLACK
  refuse_first(
      path,
      bad,
      "xVelocity",
      lambda row: f"xVelocity {vx[row]:g} m/s contradicts drivingDirection "
      f"{direction[row]} of track {tracks['id'].iloc[row]} (1 drives toward -x, 2 toward +x)",
  )
  centre = {
      c: tracks[c].to_numpy(np.float64) + 0.5 * tracks[s].to_numpy(np.float64)
      for c, s in (("x", "width"), ("y", "height"))
  }
  dx = np.diff(centre["x"]) - 0.5 * (vx[1:] + vx[:-1]) * constants.DT
  for column, bad in (
      ("x", np.abs(dx) > MAX_MOTION_MISMATCH),
      ("y", np.abs(np.diff(centre["y"])) > MAX_LATERAL_STEP),
  ):
    refuse_first(
        path,
        np.r_[False, bad & same_track],  # row i: the step from row i - 1
        column,
        lambda row, column=column: f"the centre jumps in {column} between frames "
        f"{tracks['frame'].iloc[row - 1]} and {tracks['frame'].iloc[row]} of "
        f"track {tracks['id'].iloc[row]} (more than xVelocity / 25 Hz + "
        f"{MAX_MOTION_MISMATCH:g} m in x, {MAX_LATERAL_STEP:g} m in y)",
    )


def check_recording_meta(path: Path, rec_meta: pd.DataFrame) -> None:
  """frameRate = 25 and both lane-marking lists well formed."""
  if int(rec_meta["frameRate"].iloc[0]) != constants.FRAME_RATE_HZ:
    raise DataError(
        path,
        f"frame rate {rec_meta['frameRate'].iloc[0]}, " f"expected {constants.FRAME_RATE_HZ}",
        row=2,
        column="frameRate",
    )
  for column in ("upperLaneMarkings", "lowerLaneMarkings"):
    lane_markings(path, rec_meta[column].iloc[0], column)


def check_tracks_meta(meta_path: Path, meta: pd.DataFrame) -> None:
  """finalFrame = initialFrame + numFrames - 1 and every track id once."""
  bad = (meta["finalFrame"] != meta["initialFrame"] + meta["numFrames"] - 1).to_numpy()
  refuse_first(
      meta_path, bad, "finalFrame", lambda row: "finalFrame is not initialFrame + numFrames - 1"
  )
  meta_ids = meta["id"].to_numpy(np.int64)
  bad = meta["id"].duplicated().to_numpy()
  refuse_first(meta_path, bad, "id", lambda row: f"track id {meta_ids[row]} appears twice")


def check_track_ids(
    path: Path, meta_path: Path, tracks: pd.DataFrame, meta_ids: np.ndarray
) -> None:
  """Every track id and non-zero neighbour id of the tracks file is one of tracksMeta's."""
  size = meta_ids.max() + 1
  known = np.zeros(size + 1, bool)
  known[meta_ids] = True
  for column in ("id", *NEIGHBOUR_COLUMNS):
    values = tracks[column].to_numpy(np.int64)
    bad = (values != 0) | (column == "id")
    bad &= ~known[np.clip(values, 0, size)]
    refuse_first(
        path,
        bad,
        column,
        lambda row, values=values: f"track id {values[row]} does not exist in {meta_path.name}",
    )


def track_rows(
    path: Path, meta_path: Path, meta: pd.DataFrame, ids: np.ndarray, frames: np.ndarray
):
  """(first_row, first_frame, num_frames), each (max_id + 1,) per track id, once the rows
  are checked to be grouped by track with consecutive frames from the track's initialFrame
  and as many as tracksMeta's numFrames."""
  meta_ids = meta["id"].to_numpy(np.int64)
  size = meta_ids.max() + 1
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
  refuse_first(
      path,
      bad,
      "frame",
      lambda row: f"frames of track {ids[row]} are not consecutive from its "
      f"initialFrame {meta_first[ids[row]]} (rows sorted by id, then frame)",
  )
  num_frames = np.zeros(size, np.int64)
  num_frames[ids[starts]] = np.diff(np.r_[starts, len(ids)])
  bad = num_frames[meta_ids] != meta_num[meta_ids]
  refuse_first(
      meta_path,
      bad,
      "numFrames",
      lambda row: f"track {meta_ids[row]} has {num_frames[meta_ids[row]]} rows "
      f"in {path.name} (truncated?)",
  )
  return first_row, meta_first, num_frames
