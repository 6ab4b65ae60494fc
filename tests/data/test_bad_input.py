"""Each bad-input case -> DataError naming file, row and column; no cache damage."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from cvmdx_jax.data import dataset, extract, highd
from cvmdx_jax.data.errors import DataError
from tests.data.conftest import write_recording

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
  missing = highd.TRACKS_COLUMNS[len(last[-1].split(","))]  # first column cut off
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
@pytest.mark.parametrize("name, line, field, value, column", [
    ("01_tracks.csv", 7, 2, "1e30", "x"),
    ("01_tracks.csv", 7, 6, "1e40", "xVelocity"),
    ("01_tracks.csv", 8, 4, "-4.00", "width"),
    ("01_tracks.csv", 9, 24, "6.5", "laneId"),
    ("01_tracks.csv", 10, 9, "45.0", "yAcceleration"),
    ("01_tracks.csv", 11, 1, "1e40", "id"),
    ("01_tracksMeta.csv", 3, 2, "0.00", "height"),
    ("01_tracksMeta.csv", 2, 4, "299", "finalFrame"),
    ("01_tracksMeta.csv", 3, 0, "1", "id"),  # duplicate id
    ("01_tracksMeta.csv", 5, 8, "1e300", "traveledDistance"),
])
def test_values_outside_physical_ranges(highd_dir, name, line, field, value, column):
  _edit_line(highd_dir / name, line, field, value)
  _expect(highd_dir, name, line, column)


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
  _edit_line(highd_dir / "01_recordingMeta.csv", 2, 2, "TRUE")
  _expect(highd_dir, "01_recordingMeta.csv", 2, "locationId")


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


@pytest.mark.parametrize("v0, message", [(-5.0, "'v0' is negative"),
                                         (np.nan, "'v0' holds NaN")])
def test_negative_or_nonfinite_v0_refused(v0, message):
  from cvmdx_jax.inference import predictor as predict
  from cvmdx_jax.data import scenarios as scenarios_lib
  arrays = {name: np.zeros((3, *shape), dtype) for name, (shape, dtype)
            in scenarios_lib.FIELDS.items()}
  arrays["v0"][2] = v0
  scen = scenarios_lib.Scenarios(**arrays)
  with pytest.raises(ValueError, match=f"{message}.*scenario 2"):
    scen.validate()
  with pytest.raises(ValueError, match=f"{message}.*scenario 2"):
    scen.validate(fields=predict.INPUT_FIELDS, dtypes=False)


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
      [sys.executable, "experiments/make_dataset.py", "--config=configs/dataset.py:tiny",
       f"--data_dir={out}", "--config.source=highd", f"--config.highd_dir={highd_dir}",
       "--config.splits.train=(1,)", "--config.splits.val=(3,)", "--config.splits.test=(2,)"],
      cwd=ROOT, capture_output=True, text=True, env={"PYTHONPATH": str(ROOT),
                                                     "JAX_PLATFORMS": "cpu"})
  assert result.returncode != 0
  assert "01_tracks.csv, row 9, column 'y'" in result.stderr
  assert not (out / "cache").exists()
