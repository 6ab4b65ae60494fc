"""Each bad-input case -> DataError naming file, row and column; no cache damage."""

import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

from cvmdx_jax.data import dataset, extract, highd
from cvmdx_jax.data.errors import DataError, DataWarning
from tests.data.conftest import write_recording
from tests.subprocess_env import pythonpath

ROOT = Path(__file__).resolve().parents[2]


def _edit_line(path: Path, line: int, field: int, value: str) -> None:
  lines = path.read_text().splitlines()
  cells = lines[line - 1].split(",")
  cells[field] = value
  lines[line - 1] = ",".join(cells)
  path.write_text("\n".join(lines) + "\n")


def _expect(highd_dir, name, row, column):
  with pytest.raises(DataError) as info:
    highd.read_recording(highd_dir, 1)
  err = info.value
  assert Path(err.path).name == name and err.row == row and err.column == column
  assert name in str(err)
  return err


def test_missing_file(highd_dir):
  (highd_dir / "01_tracksMeta.csv").unlink()
  _expect(highd_dir, "01_tracksMeta.csv", None, None)


def test_misnamed_column(highd_dir):
  path = highd_dir / "01_tracks.csv"
  path.write_text(path.read_text().replace("xVelocity", "xVel", 1))
  _expect(highd_dir, "01_tracks.csv", 1, "xVelocity")


def test_non_numeric_cell(highd_dir):
  _edit_line(highd_dir / "01_tracks.csv", 7, 2, "abc")
  _expect(highd_dir, "01_tracks.csv", 7, "x")


def test_nan_cell(highd_dir):
  _edit_line(highd_dir / "01_tracks.csv", 9, 3, "")
  _expect(highd_dir, "01_tracks.csv", 9, "y")


def test_truncated_file(highd_dir):
  path = highd_dir / "01_tracks.csv"
  data = path.read_bytes()
  path.write_bytes(data[:-40])  # the last row loses its last fields
  last = data[:-40].decode().splitlines()
  cut = highd.TRACKS_COLUMNS[len(last[-1].split(",")) :]
  missing = [c for c in cut if c in highd.READ_COLUMNS["tracks"]][0]  # first one read
  with warnings.catch_warnings():
    warnings.simplefilter("error")  # no warning about the unread columns before the error
    err = _expect(highd_dir, "01_tracks.csv", len(last), missing)
  assert "truncated" in str(err)


def test_truncated_at_row_boundary(highd_dir):
  path = highd_dir / "01_tracks.csv"
  lines = path.read_text().splitlines()
  path.write_text("\n".join(lines[:-10]) + "\n")  # track 5 loses 10 rows
  _expect(highd_dir, "01_tracksMeta.csv", 6, "numFrames")


def test_unknown_neighbour_id(highd_dir):
  _edit_line(highd_dir / "01_tracks.csv", 5, 16, "999")  # precedingId of row 5
  err = _expect(highd_dir, "01_tracks.csv", 5, "precedingId")
  assert "999" in str(err)


def test_inconsistent_frames(highd_dir):
  _edit_line(highd_dir / "01_tracks.csv", 12, 0, "500")
  _expect(highd_dir, "01_tracks.csv", 12, "frame")


# Lines of the conftest recording: tracks 2-301 vehicle 1 (direction 2), 602-901 vehicle 3
# (direction 1); tracksMeta line k + 1 = vehicle k. Fields: tracks x 2, width 4,
# xVelocity 6, laneId 24; tracksMeta height 2, finalFrame 4, drivingDirection 7.
@pytest.mark.parametrize(
    "name, line, field, value, column",
    [
        ("01_tracks.csv", 7, 2, "1e30", "x"),
        ("01_tracks.csv", 7, 6, "1e40", "xVelocity"),
        ("01_tracks.csv", 8, 4, "-4.00", "width"),
        ("01_tracks.csv", 9, 24, "6.5", "laneId"),
        ("01_tracks.csv", 11, 1, "1e40", "id"),
        ("01_tracksMeta.csv", 2, 4, "299", "finalFrame"),
        ("01_tracksMeta.csv", 3, 0, "1", "id"),  # duplicate id
    ],
)
def test_values_outside_physical_ranges(highd_dir, name, line, field, value, column):
  _edit_line(highd_dir / name, line, field, value)
  _expect(highd_dir, name, line, column)


def _expect_warning(highd_dir, name, row, column):
  """The recording reads exactly like the clean one, with one DataWarning at the cell."""
  clean = highd.read_recording(highd_dir, 2)  # the same content as recording 1
  with pytest.warns(DataWarning) as record:
    rec = highd.read_recording(highd_dir, 1)
  assert [(Path(w.message.path).name, w.message.row, w.message.column) for w in record] == [
      (name, row, column)
  ]
  assert name in str(record[0].message) and "not read" in str(record[0].message)
  for field in ("track_id", "frame", "lane", "direction", "pos", "vel", "neighbours"):
    np.testing.assert_array_equal(getattr(rec, field), getattr(clean, field))


# Fields: tracks yAcceleration 9, dhw 12, ttc 14; tracksMeta width 1, height 2, class 6,
# traveledDistance 8; recordingMeta locationId 2, month 4.
@pytest.mark.parametrize(
    "name, line, field, value, column",
    [
        ("01_tracks.csv", 10, 14, "2.7e14", "ttc"),  # another exporter's "no leader"
        ("01_tracks.csv", 10, 14, "inf", "ttc"),
        ("01_tracks.csv", 11, 12, "abc", "dhw"),
        ("01_tracks.csv", 10, 9, "45.0", "yAcceleration"),
        ("01_tracksMeta.csv", 3, 2, "0.00", "height"),
        ("01_tracksMeta.csv", 4, 1, "", "width"),
        ("01_tracksMeta.csv", 5, 8, "1e300", "traveledDistance"),
        ("01_tracksMeta.csv", 2, 6, "", "class"),
        ("01_recordingMeta.csv", 2, 4, "", "month"),
    ],
)
def test_bad_cell_in_an_unread_column_is_a_warning(highd_dir, name, line, field, value, column):
  _edit_line(highd_dir / name, line, field, value)
  _expect_warning(highd_dir, name, line, column)


def test_unread_column_warning_counts_cells_and_waits_for_the_read_columns(highd_dir):
  path = highd_dir / "01_tracks.csv"
  for line in (12, 7, 30):
    _edit_line(path, line, 14, "1e15")
  with pytest.warns(DataWarning, match=r"row 7, column 'ttc'.*3 cells") as record:
    highd.read_recording(highd_dir, 1)
  assert len(record) == 1
  _edit_line(path, 40, 2, "1e30")  # x is read: an error, and no warning before it
  with warnings.catch_warnings():
    warnings.simplefilter("error")
    _expect(highd_dir, "01_tracks.csv", 40, "x")


def test_blank_line_non_utf8_and_boolean_are_located(highd_dir):
  path = highd_dir / "01_tracks.csv"
  lines = path.read_text().splitlines()
  path.write_text("\n".join(lines[:9] + [""] + lines[9:]) + "\n\n")  # line 10 blank
  _expect(highd_dir, "01_tracks.csv", 10, "frame")
  cells = lines[11].split(",")
  lines[11] = ",".join(cells[:3] + ["\udcff"] + cells[4:])  # y of line 12
  path.write_bytes("\n".join(lines).encode("utf-8", "surrogateescape"))
  _expect(highd_dir, "01_tracks.csv", 12, "y")
  write_recording(highd_dir, 1)
  _edit_line(highd_dir / "01_recordingMeta.csv", 2, 2, "TRUE")  # locationId is not read
  _expect_warning(highd_dir, "01_recordingMeta.csv", 2, "locationId")
  _edit_line(highd_dir / "01_recordingMeta.csv", 2, 1, "TRUE")
  _expect(highd_dir, "01_recordingMeta.csv", 2, "frameRate")


def test_swapped_driving_direction(highd_dir):
  _edit_line(highd_dir / "01_tracksMeta.csv", 4, 7, "2")  # vehicle 3 drives toward -x
  err = _expect(highd_dir, "01_tracks.csv", 602, "xVelocity")
  assert "contradicts drivingDirection 2" in str(err)


def test_position_jump(highd_dir):
  path = highd_dir / "01_tracks.csv"
  x = float(path.read_text().splitlines()[49].split(",")[2])
  _edit_line(path, 50, 2, f"{x + 3:.2f}")  # 3 m ahead of its velocity
  _expect(highd_dir, "01_tracks.csv", 50, "x")


@pytest.mark.parametrize("markings", ["8.0;abc;16.0", "8.0", "8.0;16.0;12.0", "8.0;1e30"])
def test_malformed_lane_markings(highd_dir, markings):
  path = highd_dir / "01_recordingMeta.csv"
  path.write_text(path.read_text().replace("8.0;12.0;16.0;20.0", markings))
  _expect(highd_dir, "01_recordingMeta.csv", 2, "upperLaneMarkings")


def test_recording_without_lane_change(tmp_path):
  write_recording(tmp_path, 1, vehicles=(2, 4, 5))
  config = extract.ExtractionConfig(balance=False)
  scen = highd.load_scenarios(tmp_path, [1], config)
  assert len(scen) > 0 and np.all(scen.label == 0) and np.all(scen.time_to_lane_change == -1)
  with pytest.raises(DataError, match="empty selection"):  # nothing to balance against
    highd.load_scenarios(tmp_path, [1], extract.ExtractionConfig(balance=True))


@pytest.mark.parametrize("v0, message", [(-5.0, "'v0' is negative"), (np.nan, "'v0' holds NaN")])
def test_negative_or_nonfinite_v0_refused(v0, message):
  from cvmdx_jax.data import scenarios as scenarios_lib
  from cvmdx_jax.inference import predictor_inputs

  arrays = {
      name: np.zeros((3, *shape), dtype) for name, (shape, dtype) in scenarios_lib.FIELDS.items()
  }
  arrays["v0"][2] = v0
  scen = scenarios_lib.Scenarios(**arrays)
  with pytest.raises(ValueError, match=f"{message}.*scenario 2"):
    scen.validate()
  with pytest.raises(ValueError, match=f"{message}.*scenario 2"):
    scen.validate(fields=predictor_inputs.INPUT_FIELDS, dtypes=False)


def test_empty_selection(highd_dir):
  with pytest.raises(DataError, match="empty selection"):
    highd.load_scenarios(highd_dir, [])


def test_bad_input_leaves_cache_intact(highd_config, highd_dir, tmp_path):
  out = tmp_path / "out"
  dataset.build(highd_config(), out)
  before = {p.name: p.read_bytes() for p in (out / "cache").iterdir()}
  _edit_line(highd_dir / "02_tracks.csv", 9, 3, "")
  config = highd_config()
  config.extraction.kl_stride_s = 2.0  # other settings: a rebuild is needed, and fails
  with pytest.raises(DataError):
    dataset.build(config, out)
  assert {p.name: p.read_bytes() for p in (out / "cache").iterdir()} == before


def test_make_dataset_exits_nonzero_without_cache(highd_dir, tmp_path):
  _edit_line(highd_dir / "01_tracks.csv", 9, 3, "")
  out = tmp_path / "out"
  result = subprocess.run(
      [
          sys.executable,
          "experiments/make_dataset.py",
          "--config=configs/dataset.py:tiny",
          f"--data_dir={out}",
          "--config.source=highd",
          f"--config.highd_dir={highd_dir}",
          "--config.splits.train=(1,)",
          "--config.splits.val=(3,)",
          "--config.splits.test=(2,)",
      ],
      cwd=ROOT,
      capture_output=True,
      text=True,
      env={"PYTHONPATH": pythonpath(), "JAX_PLATFORMS": "cpu"},
  )
  assert result.returncode != 0
  assert "01_tracks.csv, row 9, column 'y'" in result.stderr
  assert not (out / "cache").exists()


def _rename(directory: Path, recording_id: int, prefix: str) -> None:
  for kind, path in highd.recording_paths(directory, recording_id).items():
    path.rename(directory / f"{prefix}_{kind}.csv")


def test_recording_names_with_any_digit_count(tmp_path):
  """1_*.csv and 002_*.csv are recordings 1 and 2, read from their own files; a sibling
  missing under that prefix is named as the user would have written it."""
  from configs import dataset as dataset_config

  for recording_id, prefix in ((1, "1"), (2, "002"), (3, "03")):
    write_recording(tmp_path, recording_id)
    _rename(tmp_path, recording_id, prefix)
  (tmp_path / "ref").mkdir()
  write_recording(tmp_path / "ref", 1)
  assert highd.available_recordings(tmp_path) == [1, 2, 3]
  assert highd.recording_paths(tmp_path, 2)["tracksMeta"] == tmp_path / "002_tracksMeta.csv"
  rec, ref = highd.read_recording(tmp_path, 1), highd.read_recording(tmp_path / "ref", 1)
  assert Path(rec.path).name == "1_tracks.csv"
  np.testing.assert_array_equal(rec.pos, ref.pos)
  config = dataset_config.get_config("tiny")
  config.source, config.highd_dir = "highd", str(tmp_path)
  config.splits.train, config.splits.val, config.splits.test = (1,), (2,), (3,)
  splits = dataset.build(config, tmp_path / "out")
  assert {name: set(np.unique(s.recording_id)) for name, s in splits.items()} == {
      "train": {1},
      "val": {2},
      "test": {3},
  }
  (tmp_path / "002_recordingMeta.csv").rename(tmp_path / "02_recordingMeta.csv")
  with pytest.raises(DataError, match="002_recordingMeta.csv: file not found"):
    highd.read_recording(tmp_path, 2)


def test_two_tracks_files_of_one_recording_are_refused_before_reading(
    highd_dir, tmp_path, highd_config
):
  (highd_dir / "1_tracks.csv").write_bytes((highd_dir / "01_tracks.csv").read_bytes())
  with pytest.raises(
      DataError, match=r"recording 1 has 2 tracks files \(01_tracks.csv, " r"1_tracks.csv\)"
  ):
    highd.read_recording(highd_dir, 1)
  with pytest.raises(DataError, match="recording 1 has 2 tracks files"):
    dataset.build(highd_config(), tmp_path / "out")
  assert not (tmp_path / "out" / "cache").exists()
