"""Hostile highD files: refused (or read) in bounded memory with a short `DataError` naming
the file, line and column; the reader's memory does not grow with a file's extra columns
or an over-long line (measured in a fresh process with `ru_maxrss`)."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from cvmdx_jax.data import highd, highd_csv, highd_format
from cvmdx_jax.data.errors import DataError
from tests.data.conftest import write_recording
from tests.subprocess_env import environ

MIB = 1 << 20


def _tracks(directory: Path) -> Path:
  return highd.recording_paths(directory, 1)["tracks"]


def _error(directory: Path) -> DataError:
  with pytest.raises(DataError) as info:
    highd.read_recording(directory, 1)
  assert len(str(info.value)) < 400 + len(str(directory))  # short, whatever the file holds
  return info.value


def _same(a: highd.Recording, b: highd.Recording) -> None:
  for name in ("track_id", "frame", "lane", "direction", "pos", "vel", "neighbours"):
    np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


def _extra_columns(path: Path, count: int) -> None:
  """`count` more columns (header names and cells) on every line of `path`."""
  lines = path.read_text().splitlines()
  extra_names = "".join(f",extra{i}" for i in range(count))
  extra_cells = ",7" * count
  path.write_text(
      "\n".join([lines[0] + extra_names] + [row + extra_cells for row in lines[1:]]) + "\n"
  )


def test_extra_header_columns_are_skipped_not_stored(highd_dir):
  clean = highd.read_recording(highd_dir, 1)
  _extra_columns(_tracks(highd_dir), 500)  # 500 more columns of 1,500 rows
  _same(highd.read_recording(highd_dir, 1), clean)


def test_extra_fields_on_the_first_data_row_blame_that_row(highd_dir):
  path = _tracks(highd_dir)
  lines = path.read_text().splitlines()
  lines[1] += ",1,2"  # pandas would take column 1 as the index and shift every column
  path.write_text("\n".join(lines) + "\n")
  err = _error(highd_dir)
  assert (err.row, err.column) == (2, None)
  assert f"{len(highd.TRACKS_COLUMNS) + 2} fields, the header has" in str(err)


@pytest.mark.parametrize("line", [2, 700])
def test_an_over_long_line_is_a_short_error_at_its_line(highd_dir, line):
  path = _tracks(highd_dir)
  lines = path.read_text().splitlines()
  lines[line - 1] = "9" * (20 * MIB)  # one 20 MB cell, no newline for 20 blocks
  path.write_text("\n".join(lines) + "\n")
  err = _error(highd_dir)
  assert err.row == line and f"longer than {highd_format.MAX_LINE_BYTES} bytes" in str(err)


@pytest.mark.parametrize("size", [64 * MIB, 4 << 30])  # NULs within / beyond the size bound
def test_a_file_of_nul_bytes_fails_fast(highd_dir, size):
  path = _tracks(highd_dir)
  with path.open("wb") as f:
    f.truncate(size)  # sparse: no disk used
  err = _error(highd_dir)
  if size <= highd_format.MAX_FILE_BYTES:
    assert err.row == 1 and "NUL byte" in str(err)
  else:
    assert err.row is None and f"{size} bytes, more than any highD" in str(err)


def test_nul_and_non_utf8_bytes_name_line_and_column(highd_dir):
  path = _tracks(highd_dir)
  data = path.read_bytes().split(b"\n")
  cells = data[9].split(b",")
  cells[3] = b"1\x002"  # y of line 10
  data[9] = b",".join(cells)
  path.write_bytes(b"\n".join(data))
  err = _error(highd_dir)
  assert (err.row, err.column) == (10, "y") and "NUL byte" in str(err)


def test_more_rows_than_the_bound(highd_dir, monkeypatch):
  monkeypatch.setattr(highd_csv, "MAX_ROWS", 100)
  monkeypatch.setattr(highd_csv, "BLOCK_BYTES", 4096)  # the bound is checked per block
  err = _error(highd_dir)
  assert Path(err.path).name == "01_tracks.csv" and "more than 100 rows" in str(err)


def test_a_long_non_numeric_cell_is_quoted_short(highd_dir):
  path = _tracks(highd_dir)
  lines = path.read_text().splitlines()
  cells = lines[4].split(",")
  cells[2] = "x" * 60_000  # x of line 5, below the line bound
  lines[4] = ",".join(cells)
  path.write_text("\n".join(lines) + "\n")
  err = _error(highd_dir)
  assert (err.row, err.column) == (5, "x") and "non-numeric value 'xxx" in str(err)


# The peak resident memory (VmHWM) of this process alone: reset first (Linux's clear_refs
# "5"), as a forked child starts with its parent's peak, here the writer of the test files.
_MEASURE = """
import json, re, sys
from pathlib import Path
from cvmdx_jax.data import highd
from cvmdx_jax.data.errors import DataError
Path("/proc/self/clear_refs").write_text("5")
peaks = []
for directory in sys.argv[1:]:
  try:
    highd.read_recording(directory, 1)
  except DataError:
    pass
  status = Path("/proc/self/status").read_text()
  peaks.append(int(re.search(r"VmHWM:\\s+(\\d+) kB", status).group(1)) * 1024)
print(json.dumps(peaks))
"""


def _peak_bytes(directories: list[Path]) -> list[int]:
  """Peak resident memory of a fresh process after reading each directory in turn."""
  proc = subprocess.run(
      [sys.executable, "-c", _MEASURE, *map(str, directories)],
      env=environ(JAX_PLATFORMS="cpu"),
      capture_output=True,
      text=True,
      timeout=300,
      check=True,
  )
  return json.loads(proc.stdout)


def _hostile_dirs(root: Path, line_bytes: int) -> list[Path]:
  """A clean recording, then one with `line_bytes` of digits on line 3 and one with 2,000
  extra columns."""
  dirs = [root / name for name in ("clean", "long_line", "wide")]
  for d in dirs:
    d.mkdir()
    write_recording(d)
  path = _tracks(dirs[1])
  lines = path.read_text().splitlines()
  lines[2] = "1" * line_bytes
  path.write_text("\n".join(lines) + "\n")
  _extra_columns(_tracks(dirs[2]), 2000)
  return dirs


def test_memory_does_not_grow_with_a_hostile_file(tmp_path):
  clean, long_line, wide = _peak_bytes(_hostile_dirs(tmp_path, 40 * MIB))
  assert long_line - clean < 32 * MIB  # the 40 MB line is never held whole
  assert wide - clean < 64 * MIB  # 2,000 extra columns x 1,500 rows are not stored


@pytest.mark.slow
def test_a_200_mb_line_stays_under_1_gb(tmp_path):
  peaks = _peak_bytes(_hostile_dirs(tmp_path, 200 * MIB))
  assert max(peaks) < 1 << 30 and peaks[1] - peaks[0] < 32 * MIB
