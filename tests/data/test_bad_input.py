"""Each bad-input case -> DataError naming file, row and column; no cache damage."""

import subprocess
import sys
from pathlib import Path

import pytest

from cvmdx_jax.data import dataset, highd
from cvmdx_jax.data.errors import DataError

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
