"""Seeded random corruption of the conftest recording: the raw highD reader either reads it
correctly or raises `DataError` naming file, row and column; never another exception, and a
failed `dataset.build` leaves the cache as it was.

Each case applies one corruption to one file and states what it must give: `fail` (must
raise), the file the error must name (None: any file of the recording), the row and column
(ANY: some value; None: not located, for whole-file problems), `same` (must read exactly
like the clean recording) and `warns` (a `DataWarning` must name this (kind, row, column):
a bad cell in a column the reader does not use).
"""

import dataclasses
import math
import warnings
from pathlib import Path

import numpy as np
import pytest

from cvmdx_jax.data import cache, dataset, highd
from cvmdx_jax.data import scenarios as scenarios_lib
from cvmdx_jax.data.errors import DataError, DataWarning
from tests.data.conftest import write_recording

ANY = "any"
COLUMNS = {
    "tracks": highd.TRACKS_COLUMNS,
    "tracksMeta": highd.TRACKS_META_COLUMNS,
    "recordingMeta": highd.RECORDING_META_COLUMNS,
}
UNUSED_TEXT = ("class", "month", "weekDay", "startTime")
NA_TEXT = ("", "nan", "NaN", "NA", "null")  # what pandas reads as a missing cell
# Index of the last column the reader uses, per file (the later ones it only warns about).
LAST_READ = {
    kind: max(COLUMNS[kind].index(c) for c in highd.READ_COLUMNS[kind]) for kind in COLUMNS
}
MARKINGS = ("upperLaneMarkings", "lowerLaneMarkings")
NAN_LIKE = ["", "nan", "NaN", "NA", "null", "inf", "-inf", " "]
NOT_NUMBERS = [
    "abc",
    "1.2.3",
    "--1",
    "x1",
    "#",
    "e5",
    "1e",
    "TRUE",
    "0x1A",
    "1_000",
    "½",
    "\U0001d7d9",
]
ABSURD = [
    "1e30",
    "-1e30",
    "1e40",
    "-1e40",
    "1e308",
    "1e309",
    "-1e9",
    "2147483648",
    "9.999e15",
    "-0",
    "0",
    "-1",
    "1e-30",
    "123456789",
    "0.5",
]
BAD_MARKINGS = [
    "",
    "abc",
    "8.0;;12.0",
    "12.0;8.0",
    "8.0",
    "8.0;12.0;",
    "1e40;2e40",
    "nan;1",
    "8.0;8.0",
    "inf;1e3",
]


@dataclasses.dataclass
class Case:
  name: str
  files: dict  # kind -> bytes or None (missing)
  fail: bool = True
  kind: str | None = None
  row: object = ANY
  column: object = ANY
  same: bool = False
  warns: tuple | None = None


def _split(data: bytes) -> list:
  return data.decode().split("\n")  # the last item is "" (trailing newline)


def _join(lines) -> bytes:
  return "\n".join(lines).encode()


def _pick(rng, seq):
  return seq[int(rng.integers(len(seq)))]


def _cell_case(rng, clean, name, values, kinds=tuple(COLUMNS)):
  """One cell of a data line set to a value from `values`."""
  kind = _pick(rng, kinds)
  lines = _split(clean[kind])
  line = int(rng.integers(2, len(lines)))  # 1-based line of a data row
  field = int(rng.integers(len(COLUMNS[kind])))
  value = _pick(rng, values)
  cells = lines[line - 1].split(",")
  cells[field] = value
  lines[line - 1] = ",".join(cells)
  return kind, COLUMNS[kind][field], line, value, {**clean, kind: _join(lines)}


def _is_number(text: str) -> bool:
  try:
    return math.isfinite(float(text))
  except ValueError:
    return False


def _cut_must_fail(kind: str, partial_line: str) -> bool:
  """Whether a data line of `kind` cut to `partial_line` lost a column the reader uses (a
  used column cut inside its value may still read, as another valid number)."""
  field = partial_line.count(",")
  return LAST_READ[kind] > field or (LAST_READ[kind] == field and not partial_line.split(",")[-1])


FILE_CASES = ("missing", "empty", "header_only", "drop_header", "bom_crlf", "cut_file", "bytes")
COLUMN_CASES = ("drop_column", "permute", "rename_column")
CELL_CASES = ("nan", "text", "absurd")
LINE_CASES = ("truncate_line", "duplicate", "delete", "swap")


def make_case(rng, clean) -> Case:
  """One variant of the clean recording's files `clean` (a corruption, or a harmless change),
  drawn with `rng`, with what reading it must give."""
  what = _pick(
      rng,
      [
          "missing",
          "empty",
          "header_only",
          "drop_column",
          "permute",
          "bom_crlf",
          "nan",
          "text",
          "truncate_line",
          "cut_file",
          "duplicate",
          "delete",
          "swap",
          "unknown_id",
          "absurd",
          "markings",
          "direction",
          "bytes",
          "drop_header",
          "rename_column",
      ],
  )
  kind = _pick(rng, tuple(COLUMNS))
  for cases, make in (
      (FILE_CASES, _file_case),
      (COLUMN_CASES, _column_case),
      (CELL_CASES, _cell_value_case),
      (LINE_CASES, _line_case),
  ):
    if what in cases:
      return make(rng, clean, what, kind)
  return _id_case(rng, clean, what)


def _file_case(rng, clean, what: str, kind: str) -> Case:
  """File `kind` missing, empty, without rows or header, with a BOM and CRLF, cut, or with
  one byte replaced by a random byte (often not UTF-8, a quote or a separator)."""
  data = clean[kind]
  lines = _split(data)
  if what == "missing":
    return Case(what, {**clean, kind: None}, kind=kind, row=None, column=None)
  if what == "empty":
    return Case(what, {**clean, kind: b""}, kind=kind, row=1, column=None)
  if what == "header_only":
    return Case(what, {**clean, kind: _join(lines[:1] + [""])}, kind=kind, row=2, column=None)
  if what == "drop_header":
    return Case(what, {**clean, kind: _join(lines[1:])}, kind=kind, row=1)
  if what == "bom_crlf":
    text = data.replace(b"\n", b"\r\n") if rng.integers(2) else data
    return Case(what, {**clean, kind: b"\xef\xbb\xbf" + text}, fail=False, same=True)
  if what == "cut_file":
    header_end = data.index(b"\n") + 1
    cut = int(rng.integers(header_end + 1, len(data) - 1))
    kept = data[:cut].decode().split("\n")
    # A cut before the last data line drops rows, which the reader always notices.
    must = len(kept) < len(lines) - 1 or _cut_must_fail(kind, kept[-1])
    return Case(what, {**clean, kind: data[:cut]}, fail=must)
  at = int(rng.integers(len(data)))
  byte = bytes([int(rng.integers(256))])
  return Case(what, {**clean, kind: data[:at] + byte + data[at + 1 :]}, fail=False)


def _column_case(rng, clean, what: str, kind: str) -> Case:
  """A column of file `kind` dropped or renamed (an error naming it), or the columns
  permuted (read the same)."""
  files = dict(clean)
  table = [line.split(",") for line in _split(clean[kind])[:-1]]
  n = len(COLUMNS[kind])
  if what == "permute":
    order = rng.permutation(n)
    files[kind] = _join([",".join(r[i] for i in order) for r in table] + [""])
    return Case(what, files, fail=False, same=True)
  field = int(rng.integers(n))
  if what == "drop_column":
    table = [r[:field] + r[field + 1 :] for r in table]
  else:
    table[0][field] = _pick(
        rng, [table[0][field] + "_", table[0][field].upper(), "", table[0][(field + 1) % n]]
    )
  files[kind] = _join([",".join(r) for r in table] + [""])
  return Case(what, files, kind=kind, row=1, column=COLUMNS[kind][field])


def _cell_value_case(rng, clean, what: str, kind: str) -> Case:
  """One cell NaN-like, text or absurd: an error where the reader reads the column, a
  warning or nothing elsewhere."""
  del kind  # `_cell_case` draws the file itself
  pool = {"nan": NAN_LIKE, "text": NOT_NUMBERS, "absurd": ABSURD}[what]
  kind, column, line, value, files = _cell_case(rng, clean, what, pool, tuple(COLUMNS))
  what = f"{what} {kind} line {line} {column}={value!r}"
  if column in UNUSED_TEXT:  # any text is fine there; an empty cell is warned about
    warns = (kind, line, column) if value.strip() in NA_TEXT else None
    return Case(what, files, fail=False, same=True, warns=warns)
  must = not _is_number(value) or abs(float(value)) > highd.ABSURD
  if column not in highd.READ_COLUMNS[kind]:  # read anyway, with a warning
    return Case(what, files, fail=False, same=True, warns=(kind, line, column) if must else None)
  if column in MARKINGS:  # a single number is not a list of markings
    must = True
  return Case(
      what,
      files,
      fail=must,
      kind=kind if must else None,
      row=line if must else ANY,
      column=column if must else ANY,
  )


def _line_case(rng, clean, what: str, kind: str) -> Case:
  """A line of file `kind` cut short, or a data line of the tracks or tracksMeta file
  duplicated, deleted or swapped with another."""
  if what == "truncate_line":
    lines = _split(clean[kind])
    line = int(rng.integers(2, len(lines)))
    text = lines[line - 1]
    cut = int(rng.integers(len(text)))
    lines[line - 1] = text[:cut]
    must = _cut_must_fail(kind, text[:cut])
    return Case(
        what,
        {**clean, kind: _join(lines)},
        fail=must,
        kind=kind,
        row=line,
        same=LAST_READ[kind] < text[:cut].count(","),
    )
  kind = _pick(rng, ("tracks", "tracksMeta"))
  lines = _split(clean[kind])
  line = int(rng.integers(2, len(lines)))
  if what == "duplicate":
    lines.insert(line, lines[line - 1])
  elif what == "delete":
    del lines[line - 1]
  else:
    other = int(rng.integers(2, len(lines)))
    if other == line:
      other = line + 1 if line + 1 < len(lines) else line - 1
    lines[line - 1], lines[other - 1] = lines[other - 1], lines[line - 1]
    if kind == "tracksMeta":  # the order of the vehicles does not matter
      return Case(what, {**clean, kind: _join(lines)}, fail=False, same=True)
  return Case(what, {**clean, kind: _join(lines)})


def _id_case(rng, clean, what: str) -> Case:
  """An unknown track id, malformed lane markings, or a vehicle's drivingDirection flipped."""
  if what == "unknown_id":
    kind = "tracks"
    lines = _split(clean[kind])
    line = int(rng.integers(2, len(lines)))
    column = _pick(rng, ("id", *highd.NEIGHBOUR_COLUMNS))
    cells = lines[line - 1].split(",")
    cells[COLUMNS[kind].index(column)] = str(_pick(rng, [6, 77, 999_999]))
    lines[line - 1] = ",".join(cells)
    return Case(what, {**clean, kind: _join(lines)}, kind=kind, row=line, column=column)
  if what == "markings":
    column = _pick(rng, MARKINGS)
    lines = _split(clean["recordingMeta"])
    cells = lines[1].split(",")
    cells[COLUMNS["recordingMeta"].index(column)] = _pick(rng, BAD_MARKINGS)
    lines[1] = ",".join(cells)
    return Case(
        what, {**clean, "recordingMeta": _join(lines)}, kind="recordingMeta", row=2, column=column
    )
  lines = _split(clean["tracksMeta"])  # "direction"
  line = int(rng.integers(2, len(lines)))
  cells = lines[line - 1].split(",")
  field = COLUMNS["tracksMeta"].index("drivingDirection")
  cells[field] = "1" if cells[field] == "2" else "2"
  lines[line - 1] = ",".join(cells)
  return Case(what, {**clean, "tracksMeta": _join(lines)}, kind="tracks", column="xVelocity")


def _write(directory: Path, files: dict) -> None:
  for kind, path in highd.recording_paths(directory, 1).items():
    path.unlink(missing_ok=True)
    if files[kind] is not None:
      path.write_bytes(files[kind])


def _same(a: highd.Recording, b: highd.Recording) -> bool:
  return all(
      np.array_equal(getattr(a, f.name), getattr(b, f.name))
      for f in dataclasses.fields(highd.Recording)
      if f.name != "path"
  )


def _sane(rec: highd.Recording) -> None:
  assert np.all(np.isfinite(rec.pos)) and np.all(np.isfinite(rec.vel))
  assert np.all(np.abs(rec.vel) <= 100) and set(np.unique(rec.direction)) <= {1, 2}
  assert np.all(rec.lane >= 1) and np.all(rec.num_frames[rec.track_id] > 0)


def _check(case: Case, directory: Path, clean_rec) -> str:
  """Reads the corrupted recording; returns 'read' or 'error', failing on a wrong answer."""
  _write(directory, case.files)
  try:
    with warnings.catch_warnings(record=True) as record:
      warnings.simplefilter("always")
      rec = highd.read_recording(directory, 1)
  except DataError as err:
    where = f"{case.name}: {err}"
    assert not case.same, where
    names = [p.name for p in highd.recording_paths(directory, 1).values()]
    assert Path(err.path).name in names, where
    if case.kind is not None:
      assert Path(err.path).name == f"01_{case.kind}.csv", where
    for field, want in (("row", case.row), ("column", case.column)):
      got = getattr(err, field)
      if want == ANY:  # a line with more fields than the header has no column
        assert got is not None or (field == "column" and "the header has" in str(err)), where
      else:
        assert got == want, where
    return "error"
  assert not case.fail, f"{case.name}: read without error"
  if case.warns is not None:
    kind, row, column = case.warns
    assert any(
        isinstance(w.message, DataWarning)
        and w.message.row == row
        and w.message.column == column
        and Path(w.message.path).name == f"01_{kind}.csv"
        for w in record
    ), case.name
  _sane(rec)
  if case.same:
    assert _same(rec, clean_rec), case.name
  return "read"


def _fake_cache(out: Path) -> dict:
  """A valid cache of other settings (so `build` must try to rebuild); its bytes."""
  scen = scenarios_lib.from_arrays(
      **{
          name: np.zeros((3, *shape), dtype)
          for name, (shape, dtype) in scenarios_lib.FIELDS.items()
      }
  )
  cache.write(out / "cache", {"train": scen, "test": scen}, {"other": True}, [])
  return {p.name: p.read_bytes() for p in (out / "cache").iterdir()}


def run_fuzz(num_cases: int, seed: int, tmp_path: Path, config) -> dict:
  """Runs `num_cases` cases; every one whose read fails is also built into a fresh
  directory (no cache may appear) and over an existing cache (it must stay byte-identical)."""
  rng = np.random.default_rng(seed)
  source = tmp_path / "rec"
  source.mkdir()
  write_recording(source, 1)
  write_recording(source, 2)  # the clean test split of `config`
  clean = {kind: path.read_bytes() for kind, path in highd.recording_paths(source, 1).items()}
  clean_rec = highd.read_recording(source, 1)
  kept = tmp_path / "kept"
  before = _fake_cache(kept)
  counts = {"read": 0, "error": 0}
  for index in range(num_cases):
    case = make_case(rng, clean)
    outcome = _check(case, source, clean_rec)
    counts[outcome] += 1
    if outcome == "error":
      for out in (tmp_path / f"fresh{index}", kept):
        with pytest.raises(DataError):
          dataset.build(config, out)
      assert not (tmp_path / f"fresh{index}" / "cache").exists()
      assert {p.name: p.read_bytes() for p in (kept / "cache").iterdir()} == before
  return counts


def _config(source: Path):
  from configs import dataset as dataset_config

  config = dataset_config.get_config("tiny")
  config.source, config.highd_dir = "highd", str(source)
  config.splits.train, config.splits.test = (1,), (2,)
  return config


def test_fuzz_highd_reader(tmp_path):
  counts = run_fuzz(120, seed=0, tmp_path=tmp_path, config=_config(tmp_path / "rec"))
  assert counts["error"] > 60 and counts["read"] > 5, counts  # both outcomes exercised


@pytest.mark.slow
def test_fuzz_highd_reader_many(tmp_path):
  counts = run_fuzz(3000, seed=1, tmp_path=tmp_path, config=_config(tmp_path / "rec"))
  assert counts["error"] > 1500 and counts["read"] > 150, counts
