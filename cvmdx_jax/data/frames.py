"""Observations of every vehicle of a highD-format recording at any frame (no futures).

The highD reader (`data.highd.read_recording`) validates the recording and moves it to each
direction's road frame; `extract.observed` builds xi / mask / v0 / psi0 exactly as the
dataset's windows (same neighbour slots, frame and units), so an observation made here at
a (track, frame) equals the reader's scenario there (`inference.observations.from_recording`
makes `Observations` of them). SUMO recordings are written in highD format
(`data.sumo_export`) and read the same way.

A vehicle can be observed at frame f when its track holds the 75 frames f - 74 .. f
(3 s of history at 25 Hz).
"""

import numpy as np
import pandas as pd

from cvmdx_jax import constants
from cvmdx_jax.data import extract, highd
from cvmdx_jax.data.errors import DataError

HISTORY = constants.T_OBS - 1  # rows of a track needed before t0


def image_centre(rec: highd.Recording, rows: np.ndarray) -> np.ndarray:
  """(N, 2) bounding-box centres of `rows` in the image frame (the road frame inverted)."""
  sign = np.where(rec.direction[rows] == 2, 1.0, -1.0)[:, None]
  return rec.pos[rows] * np.concatenate([sign, -sign], -1)


def frame_range(rec: highd.Recording) -> tuple[int, int]:
  """(first, last) frame of the recording."""
  return int(rec.frame.min()), int(rec.frame.max())


def observable_rows(rec: highd.Recording, frames) -> np.ndarray:
  """Rows of every vehicle observable at one of `frames` (3 s of history), sorted by
  (frame, track id)."""
  within = np.arange(len(rec.frame)) - rec.first_row[rec.track_id]
  rows = np.flatnonzero((within >= HISTORY) & np.isin(rec.frame, np.asarray(frames)))
  return rows[np.lexsort((rec.track_id[rows], rec.frame[rows]))]


def row_of(rec: highd.Recording, track_id: int, frame: int) -> int:
  """The row of (track_id, frame); DataError naming the recording when the frame lies
  outside the recording, the track does not exist or is not there then, or has less than
  3 s of history at that frame."""
  first, last = frame_range(rec)
  if not first <= frame <= last:
    raise DataError(
        rec.path, f"frame {frame} outside the recording (frames {first}..{last})", column="frame"
    )
  if not 0 < track_id < len(rec.num_frames) or rec.num_frames[track_id] == 0:
    raise DataError(rec.path, f"track {track_id} does not exist", column="id")
  start, count = rec.first_frame[track_id], rec.num_frames[track_id]
  if not start <= frame < start + count:
    raise DataError(
        rec.path,
        f"track {track_id} is not in frame {frame} (frames {start}.." f"{start + count - 1})",
        column="frame",
    )
  if frame - start < HISTORY:
    raise DataError(
        rec.path,
        f"track {track_id} has {frame - start + 1} frames of history "
        f"at frame {frame}, needs {HISTORY + 1} (3 s)",
        column="frame",
    )
  return int(rec.first_row[track_id] + frame - start)


def observed(rec: highd.Recording, rows: np.ndarray) -> dict:
  """`extract.observed` of the ego rows `rows` (N,) (each with 3 s of history: `row_of`,
  `observable_rows`) plus 'origin' (N, 2), their image-frame centres, and 'direction' (N,),
  their drivingDirection."""
  rows = np.asarray(rows, np.int64)
  return {
      **extract.observed(rec, rows),
      "origin": image_centre(rec, rows),
      "direction": rec.direction[rows],
  }


def rows_of(rec: highd.Recording, track_ids, frames) -> np.ndarray:
  """(N,) rows of the vehicles `track_ids` (N,) at `frames` (N,); DataError as `row_of`."""
  return np.array(
      [row_of(rec, int(t), int(f)) for t, f in zip(np.ravel(track_ids), np.ravel(frames))], np.int64
  )


def futures(rec: highd.Recording, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
  """Recorded futures of `rows` where the track lasts 5 s more: ((N, 125, 2) float64 image-
  frame centres at t0 + 1 .. t0 + 125 (NaN where unknown), (N,) bool known)."""
  rows = np.asarray(rows, np.int64)
  end = rec.first_row[rec.track_id[rows]] + rec.num_frames[rec.track_id[rows]]
  known = rows + constants.T_PRED < end
  steps = np.arange(1, constants.T_PRED + 1)
  ahead = np.where(known[:, None], rows[:, None] + steps, rows[:, None])
  centres = image_centre(rec, ahead.ravel()).reshape(len(rows), constants.T_PRED, 2)
  return np.where(known[:, None, None], centres, np.nan), known


def scene(data_dir, recording_id: int) -> dict:
  """What a drawing of the recording needs beyond `read_recording` (call that first: it
  validates the files): {'upper', 'lower': lane markings (K,) image y, m; 'length',
  'width': (max_id + 1,) vehicle sizes by track id, m (NaN where unknown)}."""
  paths = highd.recording_paths(data_dir, recording_id)
  rec_meta = pd.read_csv(paths["recordingMeta"], skipinitialspace=True)
  meta = pd.read_csv(paths["tracksMeta"], skipinitialspace=True)
  ids = meta["id"].to_numpy(np.int64)
  sizes = {}
  for name, column in (("length", "width"), ("width", "height")):
    sizes[name] = np.full(ids.max() + 1, np.nan)
    sizes[name][ids] = pd.to_numeric(meta[column], errors="coerce").to_numpy(np.float64)
  markings = {
      key: np.array([float(v) for v in str(rec_meta[column].iloc[0]).split(";")])
      for key, column in (("upper", "upperLaneMarkings"), ("lower", "lowerLaneMarkings"))
  }
  return {**markings, **sizes}
