"""Observations from raw tracks at any frame (`data.frames`) against the dataset reader."""

import numpy as np
import pandas as pd
import pytest

from cvmdx_jax.data import extract, frames, highd
from cvmdx_jax.data.errors import DataError
from tests.data.conftest import vehicle_paths, write_recording


@pytest.fixture
def rec(tmp_path):
  write_recording(tmp_path, 1)
  return highd.read_recording(tmp_path, 1)


def test_observation_at_a_readers_window_equals_its_scenario(tmp_path, rec):
  config = extract.ExtractionConfig(balance=False, lc_offsets_s=(0.5, 1.0, 2.0))
  scenarios = highd.load_scenarios(tmp_path, [1], config)
  # both directions, lane changes and keep lane, a neighbour that appears mid-history
  assert set(scenarios.track_id) == {1, 2, 3, 4, 5} and len(set(scenarios.label)) == 3
  observed = frames.observed(rec, frames.rows_of(rec, scenarios.track_id, scenarios.frame))
  for name in ("xi", "mask", "v0", "psi0", "track_id", "frame", "recording_id"):
    np.testing.assert_array_equal(observed[name], getattr(scenarios, name), name)


def test_origin_and_futures_are_the_csv_centres(tmp_path, rec):
  tracks = pd.read_csv(highd.recording_paths(tmp_path, 1)["tracks"])
  centre = {
      (i, f): (x + 2.0, y + 1.0)
      for i, f, x, y in tracks[["id", "frame", "x", "y"]].itertuples(index=False)
  }
  rows = np.array(
      [frames.row_of(rec, 1, 100), frames.row_of(rec, 3, 200), frames.row_of(rec, 4, 250)]
  )
  observed = frames.observed(rec, rows)
  np.testing.assert_allclose(
      observed["origin"], [centre[(1, 100)], centre[(3, 200)], centre[(4, 250)]], atol=1e-9
  )
  np.testing.assert_array_equal(observed["direction"], [2, 1, 1])
  future, known = frames.futures(rec, rows)
  np.testing.assert_array_equal(known, [True, False, False])  # 300 - 200 < 125 frames
  expected = [centre[(1, f)] for f in range(101, 226)]
  np.testing.assert_allclose(future[0], expected, atol=1e-9)
  assert np.isnan(future[1:]).all()


def test_observable_rows_need_three_seconds_of_history(rec):
  rows = frames.observable_rows(rec, [74, 75, 150, 174, 175])
  got = list(zip(rec.frame[rows], rec.track_id[rows]))
  # tracks 1-4 start at frame 1 (75 frames of history at 75), track 5 at frame 100
  assert got == [
      (75, 1),
      (75, 2),
      (75, 3),
      (75, 4),
      (150, 1),
      (150, 2),
      (150, 3),
      (150, 4),
      (174, 1),
      (174, 2),
      (174, 3),
      (174, 4),
      (174, 5),
      (175, 1),
      (175, 2),
      (175, 3),
      (175, 4),
      (175, 5),
  ]


@pytest.mark.parametrize(
    "track, frame, match",
    [
        (1, 301, "frame 301 outside the recording"),
        (9, 100, "track 9 does not exist"),
        (5, 50, "track 5 is not in frame 50"),
        (5, 150, "track 5 has 51 frames of history at frame 150, needs 75"),
    ],
)
def test_bad_track_or_frame_names_it(rec, track, frame, match):
  with pytest.raises(DataError, match=match):
    frames.row_of(rec, track, frame)


def test_scene_reads_markings_and_sizes(tmp_path, rec):
  scene = frames.scene(tmp_path, 1)
  np.testing.assert_array_equal(scene["upper"], [8, 12, 16, 20])
  np.testing.assert_array_equal(scene["lower"], [22, 26, 30, 34])
  assert scene["length"][list(vehicle_paths())].tolist() == [4.0] * 5
  assert scene["width"][1] == 2.0 and np.isnan(scene["width"][0])
