"""`UserError`: the one base class of the errors a user's input causes.

A flag, file, config field, dataset or run directory that is wrong raises a subclass
(`data.errors.DataError`, `config_dataclass.ConfigFieldError`,
`inference.predictor.IncompatibleRunsError`, `storage.checksums.CorruptRunError`, ...)
or `UserError` itself, with a message that names the flag, file or field. The entry
points (`cli.run`) print it as one line and exit with status 2; any other exception is a
bug and keeps its traceback. It is a `ValueError`, so callers that catch bad values
keep working.
"""


class UserError(ValueError):
  """Bad input from the user; the message names the flag, file or field at fault."""
