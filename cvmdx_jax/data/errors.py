"""`DataError`: bad input data, naming the file, row and column at fault."""


class DataError(ValueError):
  """Bad input data.

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
    if column is not None:
      where.append(f"column '{column}'")
    super().__init__(f"{', '.join(where)}: {message}")
