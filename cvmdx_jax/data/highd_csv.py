"""Reading one highD CSV file in bounded memory: `read_table(path, kind)`.

`scan` streams the file once in blocks of `BLOCK_BYTES` before pandas sees it and refuses,
naming the file and line: a file over `MAX_FILE_BYTES`, a NUL byte (a binary file), bytes
that are not UTF-8 (also naming the column), a line over `MAX_LINE_BYTES` (the message
quotes its first 40 characters), more than `MAX_ROWS` lines, and a line with more fields
than the header (pandas would take the first column of such a first data row as the index
and shift every column). pandas then parses only the format's columns (`usecols`: extra
header columns are skipped, not stored), `CHUNK_ROWS` rows at a time with quoting off (a
`"` is an ordinary character, as in the scan); each chunk's numeric columns become
float64 at once and only the columns the pipeline reads are kept, so memory grows with
rows x read columns (8 bytes each), whatever the file holds.
"""

import codecs
import csv
import dataclasses
import warnings
from pathlib import Path

import numpy as np
import pandas as pd

from cvmdx_jax.data.errors import DataError, DataWarning
from cvmdx_jax.data.highd_format import (
    ABSURD,
    COLUMNS,
    MAX_FILE_BYTES,
    MAX_LINE_BYTES,
    MAX_ROWS,
    RANGES,
    READ_COLUMNS,
    SIZE_COLUMNS,
    TEXT_COLUMNS,
)

BLOCK_BYTES = 1 << 20
CHUNK_ROWS = 1 << 17
_QUOTED = 40  # characters of an over-long line quoted in its error


def _quote(data: bytes) -> str:
  return repr(data[:_QUOTED].decode("utf-8", errors="replace")) + "..."


def _line_error(path: Path, row: int, text: bytes) -> DataError:
  return DataError(
      path,
      f"line longer than {MAX_LINE_BYTES} bytes, not a highD row " f"(starts {_quote(text)})",
      row=row,
  )


def _check_block(path: Path, block: np.ndarray, state: tuple, header: int | None) -> tuple:
  """Checks the lines that end in `block` (uint8); `state` = (line, partial, fields): the
  1-based line that `block` continues, its bytes and commas before `block`; returns the
  state after it. `header` is the header's field count (None while line 1 is read)."""
  line, partial, fields = state
  ends = np.flatnonzero(block == 10)
  commas = np.cumsum(block == 44, dtype=np.int32)
  if not len(ends):
    if partial + len(block) > MAX_LINE_BYTES:
      raise _line_error(path, line, block.tobytes())
    return line, partial + len(block), fields + int(commas[-1])
  length = np.diff(np.r_[-1, ends]) - 1
  length[0] += partial
  count = np.diff(np.r_[0, commas[ends]]) + 1
  count[0] += fields
  starts = np.r_[0, ends[:-1] + 1]
  for i in np.flatnonzero(length > MAX_LINE_BYTES)[:1]:
    raise _line_error(path, line + i, block[starts[i] : ends[i]].tobytes())
  header = int(count[0]) if header is None else header
  for i in np.flatnonzero(count > header)[:1]:
    raise DataError(path, f"{count[i]} fields, the header has {header}", row=line + i)
  tail = len(block) - ends[-1] - 1
  if tail > MAX_LINE_BYTES:
    raise _line_error(path, line + len(ends), block[ends[-1] + 1 :].tobytes())
  return line + len(ends), tail, int(commas[-1] - commas[ends[-1]])


def _bad_byte(
    path: Path, message: str, data: bytes, at: int, line: int, header: list[str]
) -> DataError:
  """DataError `message` at byte `at` of `data` (the text from the start of line `line`
  on), naming the line and the column of the byte (`DataError` cuts a long name)."""
  before = data[:at]
  row, field = line + before.count(b"\n"), before[before.rfind(b"\n") + 1 :].count(b",")
  column = header[field] if field < len(header) else None
  return DataError(path, message, row=row, column=column)


def scan(path: Path) -> list[str]:
  """Streams `path` once (module docstring); returns its header's column names."""
  size = path.stat().st_size
  if size > MAX_FILE_BYTES:
    raise DataError(
        path, f"{size} bytes, more than any highD recording " f"({MAX_FILE_BYTES} at most)"
    )
  decoder = codecs.getincrementaldecoder("utf-8")()
  state, head, current = (1, 0, 0), b"", b""  # current: the bytes of line state[0] so far
  with path.open("rb") as f:
    while block := f.read(BLOCK_BYTES):
      line = state[0]
      head += block[: MAX_LINE_BYTES + 1] if line == 1 else b""
      nul = block.find(b"\0")
      if nul >= 0:
        raise _bad_byte(
            path,
            "NUL byte: a binary file, not CSV text",
            current + block,
            len(current) + nul,
            line,
            _header(head),
        )
      pending = decoder.getstate()[0]
      try:
        decoder.decode(block)
      except UnicodeDecodeError as err:
        at = len(current) - len(pending) + err.start
        raise _bad_byte(path, "not UTF-8 text", current + block, at, line, _header(head)) from err
      state = _check_block(
          path, np.frombuffer(block, np.uint8), state, None if line == 1 else len(_header(head))
      )
      cut = block.rfind(b"\n")
      current = block[cut + 1 :] if cut >= 0 else current + block
      if state[0] > MAX_ROWS + 1:
        raise DataError(path, f"more than {MAX_ROWS} rows, more than any highD recording")
  try:
    decoder.decode(b"", final=True)
  except UnicodeDecodeError as err:
    raise _bad_byte(
        path, "not UTF-8 text", current, len(current) - 1, state[0], _header(head)
    ) from err
  return _header(head)


def _header(text: bytes) -> list[str]:
  first = text.split(b"\n")[0].decode("utf-8-sig", "replace")
  return [name.strip() for name in first.rstrip("\r").split(",")]


@dataclasses.dataclass
class _Problem:
  """The first bad cell of a column (0-based data row, message) and the bad-cell count."""

  row: int
  message: str
  count: int = 0


def _cell_problems(chunk: pd.DataFrame, name: str, bounds) -> tuple[np.ndarray, tuple | None]:
  """(column `name` of `chunk` as float64 (bad cells NaN; text: the raw column), its
  (first 0-based data row, message, bad-cell count) or None) of an empty, non-numeric,
  non-finite or out-of-`bounds` cell."""
  values = original = chunk[name]
  if name in TEXT_COLUMNS:
    bad = values.isna().to_numpy()
    first = int(np.argmax(bad))
    found = (chunk.index[first], "empty value (truncated file?)", int(bad.sum()))
    return values.to_numpy(object), found if bad.any() else None
  if pd.api.types.is_bool_dtype(values):  # pandas reads TRUE / false as booleans
    values = values.astype(str)
  numbers = (
      values if pd.api.types.is_numeric_dtype(values) else pd.to_numeric(values, errors="coerce")
  )
  x = numbers.to_numpy(np.float64)
  text = np.isnan(x) & original.notna().to_numpy()
  bad = text | ~np.isfinite(x) | _outside(name, x, bounds)
  if not bad.any():
    return x, None
  row = int(np.argmax(bad))
  if text[row]:
    message = f"non-numeric value {_short(original.iloc[row])}"
  elif not np.isfinite(x[row]):
    message = "empty, NaN or infinite value (truncated file?)"
  else:
    low, high, integer = bounds
    kind = "a whole number in" if integer else "in"
    interval = f"(0, {high}]" if name in SIZE_COLUMNS else f"[{low:g}, {high:g}]"
    message = f"value {x[row]:g} is not {kind} {interval}"
  return x, (chunk.index[row], message, int(bad.sum()))


def _short(value, limit: int = _QUOTED) -> str:
  """repr(value), cut to `limit` characters."""
  text = repr(value)
  return text if len(text) <= limit else text[:limit] + "..."


def _outside(name: str, values: np.ndarray, bounds) -> np.ndarray:
  """Finite `values` outside `bounds` = (low, high, integer) (a size: also <= 0)."""
  low, high, integer = bounds
  bad = (values > high) | (values < low) | (np.abs(values) > ABSURD)
  if name in SIZE_COLUMNS:
    bad |= values <= 0
  if integer:
    bad |= values != np.round(values)
  return bad & np.isfinite(values)


def _chunks(path: Path, columns: list[str]):
  """The data rows of `path` in DataFrames of `CHUNK_ROWS` rows (index: 0-based data row;
  blank lines kept as empty rows so that row numbers stay the file's lines)."""
  return pd.read_csv(
      path,
      usecols=columns,
      dtype={c: str for c in TEXT_COLUMNS},
      skipinitialspace=True,
      skip_blank_lines=False,
      quoting=csv.QUOTE_NONE,
      encoding="utf-8",
      chunksize=CHUNK_ROWS,
  )


def _problems_and_columns(path: Path, kind: str) -> tuple[dict, dict, int]:
  """({column: first problem}, {read column: its values}, number of rows up to the last
  non-blank one) of the data rows of `path`."""
  problems, kept, rows, filled = {}, {c: [] for c in READ_COLUMNS[kind]}, 0, 0
  for chunk in _chunks(path, list(COLUMNS[kind])):
    if chunk.empty:
      continue
    nonblank = np.flatnonzero(chunk.notna().any(axis=1).to_numpy())
    filled = chunk.index[nonblank[-1]] + 1 if len(nonblank) else filled
    rows = chunk.index[-1] + 1
    for name in COLUMNS[kind]:
      values, found = _cell_problems(chunk, name, RANGES[kind].get(name, (-ABSURD, ABSURD, False)))
      if name in kept:
        kept[name].append(values)
      if found is not None:
        first = problems.setdefault(name, _Problem(*found[:2]))
        first.count += found[2]
  blank_tail = rows - filled  # trailing blank lines: a bad (empty) cell in every column
  problems = {
      name: dataclasses.replace(p, count=p.count - blank_tail)
      for name, p in problems.items()
      if p.row < filled
  }
  columns = {name: np.concatenate(v)[:filled] for name, v in kept.items()} if filled else {}
  return problems, columns, filled


def read_table(path: Path, kind: str) -> pd.DataFrame:
  """The `READ_COLUMNS[kind]` of one CSV of `kind` ('tracks', 'tracksMeta',
  'recordingMeta'), numeric ones as float64; checks the file (`scan`), its header,
  numeric cells, NaNs and `RANGES`: DataError in `READ_COLUMNS`, DataWarning elsewhere
  (after the read columns have passed)."""
  if not path.is_file():
    raise DataError(path, "file not found")
  if path.stat().st_size == 0:
    raise DataError(path, "empty file, no header", row=1)
  header = scan(path)
  for name in COLUMNS[kind]:
    if name not in header:
      raise DataError(
          path, f"missing column (header has {_short(header, 400)})", row=1, column=name
      )
  try:
    problems, columns, rows = _problems_and_columns(path, kind)
  except pd.errors.ParserError as err:  # what `scan` did not catch
    raise DataError(path, f"unreadable CSV ({_short(str(err).strip())})") from err
  if rows == 0:
    raise DataError(path, "no data rows", row=2)
  unread = []
  for name in COLUMNS[kind]:
    if name not in problems:
      continue
    p = problems[name]
    if name in READ_COLUMNS[kind]:
      raise DataError(path, p.message, row=p.row + 2, column=name)
    cells = f"{p.count} cells of this column are bad" if p.count > 1 else "the only bad cell"
    unread.append(
        DataWarning(
            path,
            f"{p.message} ({cells}); the column is not read, the " "recording is used",
            row=p.row + 2,
            column=name,
        )
    )
  for warning in unread:
    warnings.warn(warning, stacklevel=3)
  return pd.DataFrame(columns)
