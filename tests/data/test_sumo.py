"""SUMO -> highD export: file format, frame conventions and neighbour geometry."""

import numpy as np
import pandas as pd

from configs import dataset as dataset_config
from cvmdx_jax.data import highd, sumo


def test_sumo_export_is_highd_format(tmp_path):
  cfg = dataset_config.get_config("tiny").sumo
  cfg.num_recordings, cfg.duration_s = 1, 40.0
  assert sumo.make_recordings(cfg, tmp_path)[1] > 1000
  paths = highd.recording_paths(tmp_path, 1)
  tracks = pd.read_csv(paths["tracks"])
  meta = pd.read_csv(paths["tracksMeta"])
  rec = pd.read_csv(paths["recordingMeta"])
  assert tuple(tracks.columns) == highd.TRACKS_COLUMNS
  assert tuple(meta.columns) == highd.TRACKS_META_COLUMNS
  assert tuple(rec.columns) == highd.RECORDING_META_COLUMNS
  assert tracks["frame"].min() == 1 and set(meta["class"]) <= {"Car", "Truck"}
  # Direction 1 drives toward -x in the upper lanes (2-4), direction 2 toward +x (6-8).
  t = tracks.merge(meta[["id", "drivingDirection"]], on="id")
  up, down = t[t.drivingDirection == 1], t[t.drivingDirection == 2]
  assert (up.xVelocity < 0).all() and (down.xVelocity > 0).all()
  assert set(up.laneId) <= {2, 3, 4} and set(down.laneId) <= {6, 7, 8}
  assert (meta["minXVelocity"] > 0).all()
  markings = np.array([float(v) for v in
                       f"{rec.upperLaneMarkings[0]};{rec.lowerLaneMarkings[0]}".split(";")])
  centre_y = t.y + t.height / 2
  np.testing.assert_array_equal(t.laneId, 1 + np.searchsorted(markings, centre_y))
  # Neighbours from geometry: preceding = same lane, ahead in the direction of travel;
  # leftAlongside = the lane to the driver's left, overlapping longitudinally.
  key = t.set_index(["frame", "id"])
  sign = np.where(t.drivingDirection == 2, 1.0, -1.0)
  cx = t.x + t.width / 2
  for column, lane_step, check in (("precedingId", 0, "ahead"), ("leftAlongsideId", -1, "over"),
                                   ("rightFollowingId", 1, "behind")):
    rows = t[column] > 0
    other = key.loc[list(zip(t.frame[rows], t[column][rows]))]
    s = sign[rows.to_numpy()]
    expected_lane = t.laneId[rows].to_numpy() + lane_step * s
    np.testing.assert_array_equal(other.laneId.to_numpy(), expected_lane)
    gap = s * ((other.x + other.width / 2).to_numpy() - cx[rows].to_numpy())
    reach = (other.width.to_numpy() + t.width[rows].to_numpy()) / 2
    if check == "ahead":
      assert (gap > 0).all()
    elif check == "behind":
      assert (gap < 0).all()
    else:
      assert (np.abs(gap) < reach + 0.02).all()
  # The reader accepts it and extracts lane changes of both directions.
  s = highd.load_scenarios(tmp_path, [1])
  assert len(s) > 0
