"""The ecosystem reader of the highD family, lxd-io (`Dataset` -> `Recording` -> `Track`),
opens the recordings this project writes in the official download layout
(highD-dataset-v1.0/data/NN_tracks.csv, ...), and reads the same tracks as `highd`."""

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from cvmdx_jax.data import highd
from tests.data.conftest import write_recording

lxd_io = pytest.importorskip("lxd_io")  # a test dependency (requirements.lock)


def _official_layout(root: Path, recording_ids) -> Path:
  """root/highD-dataset-v1.0 with data/ holding the recordings' CSV files (written by
  `write_recording` into data/) and the background image lxd-io requires of each."""
  dataset = root / "highD-dataset-v1.0"
  data = dataset / "data"
  data.mkdir(parents=True, exist_ok=True)
  for rid in recording_ids:
    Image.new("L", (4, 2)).save(data / f"{rid:02d}_highway.png")
  return dataset


def _same_tracks(dataset_dir: Path, recording_id: int) -> int:
  """Asserts that lxd-io and `highd.read_recording` (given the dataset folder, not data/)
  read the same tracks: ids, frames, and raw bounding boxes moved to the road frame as
  highd documents it; returns the number of rows compared."""
  ours = highd.read_recording(dataset_dir, recording_id)
  recording = lxd_io.Dataset(dataset_dir).get_recording(recording_id)
  assert sorted(recording.track_ids) == sorted(np.unique(ours.track_id).tolist())
  rows = 0
  for track_id in recording.track_ids:
    track = recording.get_track(track_id)
    mine = ours.track_id == track_id
    np.testing.assert_array_equal(track.get_data("frame"), ours.frame[mine])
    sign = 1.0 if track.get_meta_data("drivingDirection") == 2 else -1.0
    centre = np.stack(
        [
            track.get_data("x") + 0.5 * track.get_data("width"),
            track.get_data("y") + 0.5 * track.get_data("height"),
        ],
        -1,
    )
    np.testing.assert_allclose(ours.pos[mine], centre * [sign, -sign], atol=1e-9)
    velocity = np.stack([track.get_data("xVelocity"), track.get_data("yVelocity")], -1)
    np.testing.assert_allclose(ours.vel[mine], velocity * [sign, -sign], atol=1e-9)
    np.testing.assert_array_equal(track.get_data("laneId"), ours.lane[mine])
    rows += int(mine.sum())
  assert rows == len(ours.track_id)
  return rows


def test_hand_built_recordings_in_the_official_layout(tmp_path):
  dataset = _official_layout(tmp_path, (1, 2))
  for rid in (1, 2):
    write_recording(dataset / "data", rid, vehicles=(1, 2, 3, 4, 5) if rid == 1 else (1, 3))
  assert highd.available_recordings(dataset) == [1, 2]
  assert lxd_io.Dataset(dataset).recording_ids == [1, 2]
  assert _same_tracks(dataset, 1) == 300 * 4 + 201
  assert _same_tracks(dataset, 2) == 600


def test_recordings_dir_prefers_the_given_folder(tmp_path):
  assert highd.recordings_dir(tmp_path) == tmp_path  # nothing anywhere: a writer's folder
  (tmp_path / "data").mkdir()
  write_recording(tmp_path / "data", 3)
  assert highd.recordings_dir(tmp_path) == tmp_path / "data"
  # recordings in the folder itself: data/ is not looked at
  for path in (tmp_path / "data").iterdir():
    (tmp_path / path.name.replace("03_", "04_")).write_bytes(path.read_bytes())
  assert highd.recordings_dir(tmp_path) == tmp_path
  assert highd.available_recordings(tmp_path) == [4]


@pytest.mark.usefixtures("eclipse_sumo")
def test_sumo_recording_reads_the_same_with_lxd_io(tmp_path):
  from configs import dataset as dataset_config
  from cvmdx_jax.data import sumo

  cfg = dataset_config.get_config("tiny").sumo
  cfg.recordings = {"train": 1}
  cfg.duration_s = 40.0
  dataset = _official_layout(tmp_path, (1,))
  sumo.make_recordings(cfg, dataset / "data")
  assert _same_tracks(dataset, 1) > 1000
