"""The checks of config flags (`--config=configs/x.py:preset --config.a.b=v`) that the
runner (`cli.run`) makes while it parses the flags; each returns one line naming the
flag or field, or None.

- `flag_message`: an absl flag error (a config file that cannot be loaded included) as
  one line;
- `unknown_field`: the `--config.a.b` argument that named no field of the config;
- `load_failure`: any other error while the flags were parsed, as the failure of the
  config file that `--config=` names;
- `check_config`: a config flag's first problem (its file does not load or holds no
  config, a field of the wrong type or not finite, a `*_dir` field that is not a
  directory). Ranges are the typed configs' (`cli.typed_config`).
"""

import math
import re
from pathlib import Path

from absl import flags
from ml_collections import config_flags

# documented for outside use, but not exported by the package
from ml_collections.config_flags.config_flags import is_config_flag

FLAGS = flags.FLAGS
_TRACEBACK = "Traceback (most recent call last):"


def _last_error_line(lines: list[str]) -> str:
  """The exception line that ends a traceback's text, without its class path."""
  return re.sub(r"^[\w.]+: ", "", lines[-1])


def flag_message(error: Exception) -> str:
  """One line of an absl flag error; a config file's traceback becomes its last line."""
  lines = [line.strip() for line in str(error).splitlines() if line.strip()]
  if _TRACEBACK in lines:
    head = lines[0].split("Error whilst parsing config file:")[0].rstrip()
    lines = [head, _last_error_line(lines)]
  return re.sub(r"^flag (--)", r"\1", " ".join(lines))


def unknown_field(argv: list[str], error: LookupError | AttributeError) -> str | None:
  """The `--config.a.b` argument that named a field the config does not have, if any."""
  text = str(error.args[0]) if error.args else ""
  for arg in argv[1:]:
    name = arg.split("=", 1)[0]
    head, dot, path = name.lstrip("-").partition(".")
    if (
        dot
        and arg.startswith("--")
        and head in FLAGS
        and is_config_flag(FLAGS[head])
        and (text.strip("'\"") in path.split(".") or text.endswith(path))
    ):
      return name
  return None


def load_failure(argv: list[str], error: Exception) -> str | None:
  """The one line of `error`, raised while the flags were parsed, as the failure of the
  config file named in `argv` (`--config=<file>[:<arg>]`); None when `argv` names none. A
  config file is code: loading it can raise anything (a syntax error, no `get_config`, a
  JSON file that is no config module)."""
  for arg in argv[1:]:
    name, eq, value = arg.lstrip("-").partition("=")
    if arg.startswith("--") and eq and name in FLAGS and is_config_flag(FLAGS[name]):
      text = " ".join(str(error).split())[:300]
      return f"--{name}={value}: cannot load the config file ({type(error).__name__}: {text})"
  return None


def _is_number(v) -> bool:
  return isinstance(v, (int, float)) and not isinstance(v, bool)


def _leaves(config, prefix: str = ""):
  """(dotted path, value) of every non-ConfigDict field of `config`."""
  for key, value in config.items():
    if hasattr(value, "items"):
      yield from _leaves(value, f"{prefix}{key}.")
    else:
      yield f"{prefix}{key}", value


def _value_problem(value, default) -> str | None:
  """What is wrong with a field's `value` (None: nothing); `default` is its value in the
  config file without overrides."""
  if isinstance(default, tuple) and default and all(map(_is_number, default)):
    if not isinstance(value, tuple) or not all(map(_is_number, value)):
      return f"expected a tuple of numbers like {default}"
  values = value if isinstance(value, tuple) else (value,)
  if any(isinstance(v, float) and not math.isfinite(v) for v in values):
    return "must be finite"
  return None


def _dir_problem(path: str, value) -> str | None:
  """A non-empty `*_dir` field must name a directory (they are all inputs)."""
  if path.rsplit(".", 1)[-1].endswith("_dir") and isinstance(value, str) and value:
    try:
      if not Path(value).is_dir():
        return "no such directory"
    except OSError as e:  # e.g. a path component longer than the file system allows
      return f"no such directory ({e.strerror})"
  return None


def _load_problem(name: str, filename: str, error: Exception) -> str:
  """The one line of a config file that failed to load (`error`, deferred by
  config_flags to the first use of the flag's value)."""
  lines = [line.strip() for line in str(error).splitlines() if line.strip()]
  last = _last_error_line(lines) if lines else type(error).__name__
  return f"--{name}={filename}: cannot load the config file ({last})"


def check_config(name: str) -> str | None:
  """The first problem of config flag `--name` (module docstring) as a message naming the
  field; None if none."""
  flag = FLAGS[name]
  filename = config_flags.get_config_filename(flag)
  try:
    value = flag.value
    config = dict(_leaves(value))
  except (OSError, AttributeError, TypeError) as e:  # no get_config, not a config, ...
    return _load_problem(name, filename, e)
  defaults = dict(_leaves(flag.parser.parse(filename)))
  problems = [(path, _value_problem(value, defaults.get(path))) for path, value in config.items()]
  problems += [(path, _dir_problem(path, value)) for path, value in config.items()]
  for path, problem in problems:
    if problem:
      return f"--{name}.{path}={config[path]}: {problem}"
  return None
