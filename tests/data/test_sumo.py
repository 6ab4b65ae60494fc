"""SUMO -> highD export: file format, frame conventions, lane ids and neighbour geometry."""

import sys
import xml.etree.ElementTree as ET

import numpy as np
import pandas as pd
import pytest

from configs import dataset as dataset_config
from cvmdx_jax.data import errors, highd, sumo, sumo_export, sumo_network, sumo_plan


def _one_recording(lanes: int, lane_width_m: float = 3.75):
  """The tiny config reduced to one train recording of 40 s with `lanes` per direction."""
  cfg = dataset_config.get_config("tiny").sumo
  cfg.recordings = {"train": 1}
  cfg.duration_s = 40.0
  cfg.lanes, cfg.lane_width_m = (lanes,), lane_width_m
  return cfg


@pytest.mark.usefixtures("eclipse_sumo")
@pytest.mark.parametrize("lanes", [2, 4])  # 3 lanes: the tiny build of test_splits.py
def test_sumo_export_is_highd_format(tmp_path, lanes):
  cfg = _one_recording(lanes, 3.5 if lanes == 4 else 3.75)
  assert sumo.make_recordings(cfg, tmp_path)[1] > 1000
  paths = highd.recording_paths(tmp_path, 1)
  tracks = pd.read_csv(paths["tracks"])
  meta = pd.read_csv(paths["tracksMeta"])
  rec = pd.read_csv(paths["recordingMeta"])
  assert tuple(tracks.columns) == highd.TRACKS_COLUMNS
  assert tuple(meta.columns) == highd.TRACKS_META_COLUMNS
  assert tuple(rec.columns) == highd.RECORDING_META_COLUMNS
  assert tracks["frame"].min() == 1 and set(meta["class"]) <= {"Car", "Truck"}
  # Direction 1 drives toward -x in the upper lanes (2..n+1), direction 2 toward +x
  # (n+3..2n+2); with 3 lanes that is highD's 2-4 and 6-8.
  t = tracks.merge(meta[["id", "drivingDirection"]], on="id")
  up, down = t[t.drivingDirection == 1], t[t.drivingDirection == 2]
  assert (up.xVelocity < 0).all() and (down.xVelocity > 0).all()
  assert set(up.laneId) <= set(range(2, lanes + 2))
  assert set(down.laneId) <= set(range(lanes + 3, 2 * lanes + 3))
  assert len(set(up.laneId)) >= 2 and len(set(down.laneId)) >= 2
  assert (meta["minXVelocity"] > 0).all()
  upper = np.array([float(v) for v in rec.upperLaneMarkings[0].split(";")])
  lower = np.array([float(v) for v in rec.lowerLaneMarkings[0].split(";")])
  width = 3.5 if lanes == 4 else 3.75
  np.testing.assert_allclose(np.diff(upper), width)
  np.testing.assert_allclose(np.diff(lower), width)
  assert len(upper) == len(lower) == lanes + 1 and upper[-1] < lower[0]
  markings = np.r_[upper, lower]
  centre_y = t.y + t.height / 2
  np.testing.assert_array_equal(t.laneId, 1 + np.searchsorted(markings, centre_y))
  # Neighbours from geometry: preceding = same lane, ahead in the direction of travel;
  # leftAlongside = the lane to the driver's left, overlapping longitudinally.
  key = t.set_index(["frame", "id"])
  sign = np.where(t.drivingDirection == 2, 1.0, -1.0)
  cx = t.x + t.width / 2
  for column, lane_step, check in (
      ("precedingId", 0, "ahead"),
      ("leftAlongsideId", -1, "over"),
      ("rightFollowingId", 1, "behind"),
  ):
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


@pytest.mark.usefixtures("eclipse_sumo")
@pytest.mark.parametrize("lanes", [2, 3, 4])
def test_lane_ids_follow_the_sumo_network(tmp_path, lanes):
  """Vehicles placed on each lane of the netconvert network (lane centres read from the
  .net.xml) get highD's laneId: direction 1 (westbound, upper) 2 + SUMO index; direction 2
  (eastbound, lower) 2 * lanes + 2 - SUMO index (SUMO's index 0 = the rightmost lane)."""
  cfg = _one_recording(lanes, 3.5)
  plan = sumo_plan.plans(cfg)[1]
  net = sumo_network.write_network(cfg, plan.road, tmp_path)
  lane_y = {
      lane.get("id"): float(lane.get("shape").split()[0].split(",")[1])
      for lane in ET.parse(net).getroot().iter("lane")
      if lane.get("id")[0] in "EW"
  }
  assert len(lane_y) == 2 * lanes
  car = plan.types[0]
  rows, expected = [], {}
  for k, (lane_id, y) in enumerate(sorted(lane_y.items())):
    edge, index = lane_id.split("_")
    east = edge == "E"
    expected[f"v{k}"] = 2 * lanes + 2 - int(index) if east else 2 + int(index)
    for step in range(10):
      time = cfg.warmup_s + step * 0.04
      x = 500.0 + (30.0 * step * 0.04 if east else -30.0 * step * 0.04)
      rows.append(
          {
              "time": time,
              "id": f"v{k}",
              "x": x,
              "y": y,
              "angle": 90.0 if east else 270.0,
              "type": car.name,
              "speed": 30.0,
              "acc": 0.0,
          }
      )
  sumo_export.export_recording(pd.DataFrame(rows), cfg, plan, tmp_path)
  tracks = pd.read_csv(highd.recording_paths(tmp_path, 1)["tracks"])
  meta = pd.read_csv(highd.recording_paths(tmp_path, 1)["tracksMeta"])
  # Track ids follow the sorted SUMO ids (all start at frame 1).
  got = tracks.groupby("id")["laneId"].agg(set).to_dict()
  assert got == {i + 1: {expected[f"v{i}"]} for i in range(2 * lanes)}
  direction = meta.set_index("id")["drivingDirection"].to_dict()
  assert all(
      direction[i + 1] == (2 if expected[f"v{i}"] > lanes + 1 else 1) for i in range(2 * lanes)
  )


@pytest.mark.usefixtures("eclipse_sumo")
def test_recordings_are_deterministic_under_the_seed(tmp_path):
  cfg = _one_recording(2)
  cfg.duration_s = 20.0
  sumo.make_recordings(cfg, tmp_path / "a")
  sumo.make_recordings(cfg, tmp_path / "b")
  for kind, path in highd.recording_paths(tmp_path / "a", 1).items():
    assert path.read_bytes() == highd.recording_paths(tmp_path / "b", 1)[kind].read_bytes()
  assert (tmp_path / "a" / sumo.PLANS_FILE).read_text() == (
      tmp_path / "b" / sumo.PLANS_FILE
  ).read_text()


def test_without_eclipse_sumo_the_source_is_refused_naming_it(tmp_path, monkeypatch):
  monkeypatch.setitem(sys.modules, "sumo", None)  # `import sumo` raises ImportError
  with pytest.raises(errors.DataError) as e:
    sumo.make_recordings(_one_recording(2), tmp_path / "rec")
  assert str(e.value).startswith(f"file {tmp_path / 'rec'}, column 'source': ")
  assert "install eclipse-sumo" in str(e.value)
  assert not list(tmp_path.iterdir())  # nothing written
