"""Hand-built highD-format recordings with known answers.

Markings (image y, down): upper 8;12;16;20 (dir 1 lanes 2, 3, 4 centred at 10, 14, 18),
lower 22;26;30;34 (dir 2 lanes 6, 7, 8 centred at 24, 28, 32). Frames 1..300, 25 Hz.
Vehicles (length 4 m, width 2 m; positions are bounding-box centres):
  1 dir 2 (+x), 30 m/s from x = 50, lane 7 -> 6 (y 28 -> 24 over frames 140..161):
    left lane change, first frame in lane 6 = 151.
  2 dir 2, lane 7, 20 m ahead of 1 at frame 1, accelerating at 1 m/s^2; preceding of 1.
  5 dir 2, lane 8 (right of 1), from frame 100, 15 m behind 1: rightFollowing of 1.
  3 dir 1 (-x), 25 m/s from x = 400, lane 3 -> 2 (y 14 -> 10 over frames 120..161):
    right lane change, first frame in lane 2 = 141.
  4 dir 1, lane 4 (left of 3), beside 3: leftAlongside of 3.
"""

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from cvmdx_jax.data import highd

FRAMES = np.arange(1, 301)
DT = 0.04
UPPER, LOWER = (8.0, 12.0, 16.0, 20.0), (22.0, 26.0, 30.0, 34.0)


def _ramp(f, f0, f1, y0, y1):
  return y0 + (y1 - y0) * np.clip((f - f0) / (f1 - f0), 0.0, 1.0)


def vehicle_paths():
  """id -> (frames, centre x, centre y, direction)."""
  t = (FRAMES - 1) * DT
  paths = {
      1: (FRAMES, 50 + 30 * t, _ramp(FRAMES, 140, 161, 28.0, 24.0), 2),
      2: (FRAMES, 70 + 30 * t + 0.5 * t**2, np.full(300, 28.0), 2),
      3: (FRAMES, 400 - 25 * t, _ramp(FRAMES, 120, 161, 14.0, 10.0), 1),
      4: (FRAMES, 400 - 25 * t, np.full(300, 18.0), 1),
  }
  f5 = FRAMES[99:]
  paths[5] = (f5, 35 + 30 * (f5 - 1) * DT, np.full(len(f5), 32.0), 2)
  return paths


def lane_of(y):
  return 1 + np.searchsorted(np.array(UPPER + LOWER), y)


def _tracks_meta_row(vid: int, frames, x, y, direction: int) -> dict:
  """The tracksMeta row of vehicle `vid` on `frames` at centres (x, y)."""
  vx = np.gradient(x, DT)
  return {
      "id": vid,
      "width": 4.0,
      "height": 2.0,
      "initialFrame": frames[0],
      "finalFrame": frames[-1],
      "numFrames": len(frames),
      "class": "Car",
      "drivingDirection": direction,
      "traveledDistance": abs(x[-1] - x[0]),
      "minXVelocity": np.abs(vx).min(),
      "maxXVelocity": np.abs(vx).max(),
      "meanXVelocity": np.abs(vx).mean(),
      "minDHW": -1,
      "minTHW": -1,
      "minTTC": -1,
      "numLaneChanges": int(np.count_nonzero(np.diff(lane_of(y)))),
  }


def _recording_meta_row(recording_id: int) -> dict:
  """The recordingMeta row: 25 Hz, the lane markings `UPPER` and `LOWER`."""
  return {
      "id": recording_id,
      "frameRate": 25,
      "locationId": 1,
      "speedLimit": -1,
      "month": "09.2017",
      "weekDay": "Tue",
      "startTime": "08:38",
      "duration": 12.0,
      "totalDrivenDistance": 0.0,
      "totalDrivenTime": 0.0,
      "numVehicles": 5,
      "numCars": 5,
      "numTrucks": 0,
      "upperLaneMarkings": ";".join(map(str, UPPER)),
      "lowerLaneMarkings": ";".join(map(str, LOWER)),
  }


def write_recording(directory: Path, recording_id: int = 1, vehicles=(1, 2, 3, 4, 5)) -> None:
  """Writes the recording described in the module docstring (only `vehicles`)."""
  rows, meta = [], []
  neighbours = {
      1: {"precedingId": 2, "rightFollowingId": 5},
      2: {"followingId": 1},
      3: {"leftAlongsideId": 4},
      4: {"rightAlongsideId": 3},
  }
  for vid, (frames, x, y, direction) in vehicle_paths().items():
    if vid not in vehicles:
      continue
    vx = np.gradient(x, DT)
    vy = np.gradient(y, DT)
    table = {
        "frame": frames,
        "id": vid,
        "x": x - 2.0,
        "y": y - 1.0,
        "width": 4.0,
        "height": 2.0,
        "xVelocity": vx,
        "yVelocity": vy,
        # The lane-change ramps step the lateral speed within a frame; their unused
        # acceleration column is clipped into highd's physical range.
        "xAcceleration": np.gradient(vx, DT),
        "yAcceleration": np.clip(np.gradient(vy, DT), -2.0, 2.0),
        "frontSightDistance": 100.0,
        "backSightDistance": 100.0,
        "dhw": 0.0,
        "thw": 0.0,
        "ttc": 0.0,
        "precedingXVelocity": 0.0,
        "laneId": lane_of(y),
    }
    for column in highd.NEIGHBOUR_COLUMNS:
      other = neighbours.get(vid, {}).get(column, 0)
      table[column] = other if other in vehicles else 0
    rows.append(pd.DataFrame(table))
    meta.append(_tracks_meta_row(vid, frames, x, y, direction))
  paths = highd.recording_paths(directory, recording_id)
  tracks = pd.concat(rows)[list(highd.TRACKS_COLUMNS)]
  tracks.to_csv(paths["tracks"], index=False, float_format="%.2f")
  pd.DataFrame(meta).to_csv(paths["tracksMeta"], index=False, float_format="%.2f")
  pd.DataFrame([_recording_meta_row(recording_id)]).to_csv(paths["recordingMeta"], index=False)


@pytest.fixture
def highd_dir(tmp_path) -> Path:
  """A directory holding recordings 01, 02 and 03 (identical content)."""
  for recording_id in (1, 2, 3):
    write_recording(tmp_path, recording_id)
  return tmp_path


@pytest.fixture
def highd_config(highd_dir):
  """A factory of fresh `configs/dataset.py:tiny` configs reading `highd_dir`
  (recording 1 train, 3 val, 2 test, two lane-change offsets)."""
  from configs import dataset as dataset_config

  def make():
    config = dataset_config.get_config("tiny")
    config.source = "highd"
    config.highd_dir = str(highd_dir)
    config.splits.train, config.splits.val, config.splits.test = (1,), (3,), (2,)
    config.extraction.lc_offsets_s = (0.5, 1.0)
    return config

  return make
