"""The one runner of the absl entry points in `experiments/`: `run(main)`.

A user's mistake ends the same way in every script: one line
`<script>: error: <message>` on stderr naming the flag, file or field, exit status 2,
no traceback. User errors are
- a bad value of `CVMDX_ALLOCATOR` (`host_allocator`), `CVMDX_WINOGRAD` or
  `CVMDX_GROUP_NORM_BACKWARD` (`models.performance`), found before the flags;
- flag errors, found before `main` starts: an unknown flag, a value of the wrong type
  or out of range (`lower_bound=`, validators), a required flag left out, an unknown
  config preset or field, a config file that cannot be loaded, a config field that is
  not finite or out of range (the ranges live in the typed configs: `typed_config`
  builds one at parsing, e.g. `config.runs.DiffusionRunConfig.from_config`), a `*_dir`
  config field that is not a directory;
- in `main`: `app.UsageError` (stray arguments), a `ValueError` raised by this
  repository's code (`DataError`, `IncompatibleRunsError`, `CheckpointMismatchError`,
  `WorkdirLockedError`, ...: their messages name the file or field) and a missing or
  unwritable path (`FileNotFoundError`, `NotADirectoryError`, `PermissionError`, ...).
The machine failing ends the same way, exit status 2, wherever it is raised: an OSError
with errno ENOSPC, EDQUOT (disk or quota full), EROFS (read-only file system) or
ENAMETOOLONG, also one from a flag's path check, and an error of orbax/tensorstore whose
message carries such an errno (`[os_error_code='28']`, a checkpoint write on a full disk).
SIGINT (Ctrl-C) prints `<script>: error: interrupted; rerun to resume` and exits with
status 130; training resumes from its last checkpoint, other steps are redone.
Anything else keeps its traceback, also a ValueError raised inside a library (a bad
array handed to numpy or JAX is a bug of ours, not of the user).

Validators for plain flags: `input_dirs`, `output_dirs`, `presets`, `int_list`.
"""

import errno
import math
import os
import re
import sys
from collections.abc import Callable
from pathlib import Path
from typing import NoReturn

from absl import app, flags
from ml_collections import config_flags
# documented for outside use, but not exported by the package
from ml_collections.config_flags.config_flags import is_config_flag

from cvmdx_jax import host_allocator
from cvmdx_jax.config.fields import ConfigFieldError
from cvmdx_jax.models import performance
from cvmdx_jax.train import preemption

FLAGS = flags.FLAGS
USAGE_STATUS = 2
_REPO = Path(__file__).resolve().parents[1]
_OUR_CODE = ("cvmdx_jax", "configs", "experiments")
_PATH_ERRORS = (FileNotFoundError, NotADirectoryError, IsADirectoryError, FileExistsError,
                PermissionError)
_FULL = (errno.ENOSPC, errno.EDQUOT)
_MACHINE_ERRNOS = (*_FULL, errno.EROFS, errno.ENAMETOOLONG)
INTERRUPTED_STATUS = 130  # 128 + SIGINT, what a shell reports for Ctrl-C


def _script() -> str:
  return Path(sys.argv[0]).stem


def fail(message: str) -> NoReturn:
  """Prints `<script>: error: <message>` (one line) to stderr and exits with status 2."""
  print(f"{_script()}: error: {' '.join(message.split())}", file=sys.stderr)
  sys.exit(USAGE_STATUS)


def _ours(exc: BaseException) -> bool:
  """Whether `exc` was raised by (or is a class of) this repository's code."""
  if type(exc).__module__.split(".")[0] in _OUR_CODE:
    return True
  tb = exc.__traceback__
  while tb is not None and tb.tb_next is not None:
    tb = tb.tb_next
  if tb is None:
    return False
  try:
    parts = Path(tb.tb_frame.f_code.co_filename).resolve().relative_to(_REPO).parts
  except ValueError:  # outside the repository (a library, or .venv resolved elsewhere)
    return False
  return parts[0] in _OUR_CODE


def is_user_error(exc: BaseException) -> bool:
  """True for the user errors of the module docstring."""
  if isinstance(exc, (app.UsageError, *_PATH_ERRORS)):
    return True
  return isinstance(exc, ValueError) and _ours(exc)


def machine_failure(exc: BaseException) -> str | None:
  """The one-line message of a failure of the machine (module docstring), else None."""
  if isinstance(exc, OSError):
    code = exc.errno
  else:  # tensorstore's status text, e.g. "RESOURCE_EXHAUSTED: ... [os_error_code='28']"
    found = re.search(r"\[os_error_code='(\d+)'\]", str(exc))
    code = int(found.group(1)) if found else None
  if code not in _MACHINE_ERRNOS:
    return None
  hint = "; free some space and rerun (training resumes from its last checkpoint)"
  return f"{exc}{hint if code in _FULL else ''}"


def run(main: Callable[[list[str]], object], *, allocator: bool = False) -> None:
  """`absl.app.run(main)` with the user-error handling of the module docstring; with
  `allocator` (the training entry points) in a process re-executed once with the
  allocator of `host_allocator` (Linux; not for `--help`). Both check their environment
  variables first (`models.performance`, `host_allocator`)."""
  try:
    performance.current()  # a bad CVMDX_WINOGRAD etc. is one line, before any work
    if allocator:
      host_allocator.reexec_with_allocator()
  except ValueError as e:
    fail(str(e))

  def guarded(argv):
    try:
      return main(argv)
    except Exception as e:  # pylint: disable=broad-except
      message = str(e) if is_user_error(e) else machine_failure(e)
      if message is None:
        raise
      fail(message)

  try:
    app.run(guarded, flags_parser=_parse_flags)
  except preemption.Stopped as e:  # training saved at a step boundary first
    print(f"{_script()}: error: {e.message}; rerun to resume", file=sys.stderr)
    sys.exit(e.code)
  except KeyboardInterrupt:
    print(f"{_script()}: error: interrupted; rerun to resume", file=sys.stderr)
    sys.exit(INTERRUPTED_STATUS)


# ---------------------------------------------------------------- flag parsing


def _flag_message(error: Exception) -> str:
  """One line of an absl flag error; a config file's traceback becomes its last line."""
  lines = [line.strip() for line in str(error).splitlines() if line.strip()]
  if "Traceback (most recent call last):" in lines:
    head = lines[0].split("Error whilst parsing config file:")[0].rstrip()
    lines = [head, re.sub(r"^[\w.]+: ", "", lines[-1])]
  return re.sub(r"^flag (--)", r"\1", " ".join(lines))


def _unknown_field(argv: list[str], error: LookupError | AttributeError) -> str | None:
  """The `--config.a.b` argument that named a field the config does not have, if any."""
  text = str(error.args[0]) if error.args else ""
  for arg in argv[1:]:
    name = arg.split("=", 1)[0]
    head, dot, path = name.lstrip("-").partition(".")
    if (dot and arg.startswith("--") and head in FLAGS
        and is_config_flag(FLAGS[head])
        and (text.strip("'\"") in path.split(".") or text.endswith(path))):
      return name
  return None


def _parse_flags(argv: list[str]) -> list[str]:
  """`FLAGS(argv)` then the config checks; a user error exits via `fail`."""
  try:
    rest = FLAGS(argv)
  except flags.Error as e:
    fail(_flag_message(e))
  except (AttributeError, KeyError) as e:  # ml_collections: an override of no field
    name = _unknown_field(argv, e)
    if name is None:
      raise
    fail(f"{name}: no such config field")
  for name in list(FLAGS):
    if is_config_flag(FLAGS[name]) and FLAGS[name].value is not None:
      problem = check_config(name)
      if problem:
        fail(problem)
  for name, typed in _TYPED.items():
    typed.build(name)
  return rest


# ------------------------------------------------------------- config fields


def _is_number(v) -> bool:
  return isinstance(v, (int, float)) and not isinstance(v, bool)


def _leaves(config, prefix: str = ""):
  """(dotted path, value) of every non-ConfigDict field of `config`."""
  for key, value in config.items():
    if hasattr(value, "items"):
      yield from _leaves(value, f"{prefix}{key}.")
    else:
      yield f"{prefix}{key}", value


def _value_problem(path: str, value, default) -> str | None:
  """What is wrong with field `path` = `value` (None: nothing); `default` is its value
  in the config file without overrides."""
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


class TypedConfig:
  """The typed config of a config flag, built once when the flags are parsed (`value`)."""

  def __init__(self, from_config: Callable):
    self._from_config, self._value = from_config, None

  def build(self, name: str) -> None:
    """Builds it from `--name`; a bad field exits via `fail`, naming it."""
    try:
      self._value = self._from_config(FLAGS[name].value)
    except ConfigFieldError as e:
      fail(f"--{name}.{e.field}={e.value}: {e.problem}")
    except ValueError as e:
      fail(f"--{name}: {e}")

  @property
  def value(self):
    if self._value is None:
      raise RuntimeError("TypedConfig.value read before the flags were parsed (cli.run)")
    return self._value


_TYPED: dict[str, TypedConfig] = {}


def typed_config(name: str, from_config: Callable) -> TypedConfig:
  """Registers `from_config(<value of config flag --name>)`, run when `run` parses the
  flags (after the checks of `check_config`); returns the holder of its result."""
  _TYPED[name] = TypedConfig(from_config)
  return _TYPED[name]


def check_config(name: str) -> str | None:
  """The first problem of config flag `--name` (load failure, a field's type or a value
  that is not finite, a `*_dir` field that is not a directory) as a message naming the
  field; None if none. Ranges are the typed config's (`typed_config`)."""
  flag = FLAGS[name]
  filename = config_flags.get_config_filename(flag)
  try:
    config = dict(_leaves(flag.value))
  except OSError as e:  # config_flags defers a file that failed to load to first use
    last = str(e).strip().splitlines()[-1].strip()
    return f"--{name}={filename}: cannot load the config file ({last})"
  defaults = dict(_leaves(flag.parser.parse(filename)))
  problems = [(path, _value_problem(path, value, defaults.get(path)))
              for path, value in config.items()]
  problems += [(path, _dir_problem(path, value)) for path, value in config.items()]
  for path, problem in problems:
    if problem:
      return f"--{name}.{path}={config[path]}: {problem}"
  return None


# ---------------------------------------------------------------- validators


def writable(path: str | os.PathLike) -> bool:
  """Whether `path` is a writable directory or can be created as one (nothing is made)."""
  path = Path(path).absolute()
  for p in (path, *path.parents):
    if p.exists():
      return p.is_dir() and os.access(p, os.W_OK | os.X_OK)
  return False


def _path_validator(name: str, check: Callable[[str], bool], message: str) -> None:
  """Validator: flag `name` is unset or `check(value)`; an OSError of the check (a name
  too long, ...) fails the flag with `message` and the OS's reason."""

  def verify(value):
    try:
      return value is None or check(value)
    except OSError as e:
      raise flags.ValidationError(f"{message} ({e.strerror})") from e
  flags.register_validator(name, verify, message)


def input_dirs(*names: str) -> None:
  """Validators: each flag of `names`, when set, names an existing directory."""
  for name in names:
    _path_validator(name, lambda v: Path(v).is_dir(), "no such directory")


def output_dirs(*names: str) -> None:
  """Validators: each flag of `names`, when set, is a directory that can be written or
  created (`writable`)."""
  for name in names:
    _path_validator(name, writable, "cannot create or write a directory there")


def presets(name: str, get_config: Callable) -> None:
  """Validator: flag `name` is a preset that `get_config` accepts (configs/*.py)."""

  def check(value):
    try:
      get_config(value)
    except ValueError as e:
      raise flags.ValidationError(str(e)) from e
    return True
  flags.register_validator(name, check)


def int_list(name: str, low: int) -> None:
  """Validator: list flag `name` holds integers >= `low`."""
  flags.register_validator(
      name, lambda v: all(re.fullmatch(r"-?\d+", s) and int(s) >= low for s in v),
      f"expected integers >= {low}, comma-separated")
