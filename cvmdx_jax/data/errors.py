"""`DataError`: bad input data, naming the file, row and column at fault; `DataWarning`:
the same for a bad cell the pipeline does not read."""

from cvmdx_jax.errors import UserError


class _Located:
  """Message prefix `file <path>, row <row>, column '<column>': `.

  Attributes:
    path: the file (or directory) at fault.
    row: 1-based line number in the file (the header is line 1), or None.
    column: the column, field or setting at fault, or None.
  """

  def __init__(self, path, message: str, row: int | None = None, column: str | None = None):
    self.path, self.row, self.column = str(path), row, column
    where = [f"file {self.path}"]
    if row is not None:
      where.append(f"row {row}")
    if column is not None:  # a column name from a hostile header is cut short
      where.append(f"column '{str(column)[:80]}{'...' if len(str(column)) > 80 else ''}'")
    super().__init__(f"{', '.join(where)}: {message}")


class DataError(_Located, UserError):
  """Bad input data (attributes of `_Located`)."""


class DataWarning(_Located, UserWarning):
  """A bad cell in a column the pipeline does not read (attributes of `_Located`)."""
