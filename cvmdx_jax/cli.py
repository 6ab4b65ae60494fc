"""The one runner of the absl entry points in `experiments/`: `run(main)`.

A user's mistake ends the same way in every script: one line
`<script>: error: <message>` on stderr naming the flag, file or field, exit status 2,
no traceback. User errors are
- a bad value of `CVMDX_ALLOCATOR` (`host_allocator`), `CVMDX_WINOGRAD` or
  `CVMDX_GROUP_NORM_BACKWARD` (`models.performance`), found before the flags;
- flag errors, found before `main` starts: an unknown flag, a value of the wrong type
  or out of range (`lower_bound=`, validators), a required flag left out, an unknown
  config preset or field, a config file that cannot be loaded, a config field that is
  not finite or out of range (`cli_config`; the ranges live in the typed configs:
  `typed_config` builds one at parsing), a `*_dir` config field that is not a directory;
- in `main`: `app.UsageError` (stray arguments), an `errors.UserError` (the base of
  `DataError`, `ConfigFieldError`, `IncompatibleRunsError`, `CheckpointMismatchError`,
  `WorkdirLockedError`, ...: their messages name the file or field) and a missing or
  unwritable path (`FileNotFoundError`, `NotADirectoryError`, `PermissionError`, ...).
The machine failing ends the same way, exit status 2, wherever it is raised: an OSError
with errno ENOSPC, EDQUOT (disk or quota full), EROFS (read-only file system) or
ENAMETOOLONG, also one from a flag's path check, and an error of orbax/tensorstore whose
message carries such an errno (`[os_error_code='28']`, a checkpoint write on a full disk).
SIGINT (Ctrl-C) prints `<script>: error: interrupted; rerun to resume` and exits with
status 130, SIGTERM `<script>: error: terminated; rerun to resume` and status 143: both
unwind `main` first (temporary files and directories are removed, child processes such
as SUMO killed); training resumes from its last checkpoint, other steps are redone.
After a signal the process ends with `os._exit` once its output is flushed: the exit
handlers of JAX's and orbax's background threads can crash an interpreter that is
interrupted mid-computation (a segfault, status 139, instead of 130). Importing this module
from a script in `experiments/` (their first import of the package) installs the same lines
and statuses for a signal during the script's imports, before `run`.
Anything else keeps its traceback, also a plain ValueError (a bad array handed to numpy
or JAX is a bug of ours, not of the user).

Validators for plain flags: `input_dirs`, `output_dirs`, `presets`, `int_list`.
"""

import errno
import os
import re
import signal
import sys
from collections.abc import Callable
from pathlib import Path
from typing import NoReturn


def _stopped_while_importing(signum, frame) -> NoReturn:
  """SIGINT or SIGTERM before `run` installs its handlers (an entry point's imports take
  seconds; nothing has started): the signal's line of `_stop`, exit 130 or 143."""
  del frame
  what = "interrupted" if signum == signal.SIGINT else "terminated"
  print(f"{Path(sys.argv[0]).stem}: error: {what}; rerun to resume", file=sys.stderr, flush=True)
  os._exit(128 + signum)  # pylint: disable=protected-access


if Path(getattr(sys.modules["__main__"], "__file__", "") or "").parent.name == "experiments":
  if signal.getsignal(signal.SIGINT) is signal.default_int_handler:  # not ignored (nohup, &)
    signal.signal(signal.SIGINT, _stopped_while_importing)
  if signal.getsignal(signal.SIGTERM) == signal.SIG_DFL:
    signal.signal(signal.SIGTERM, _stopped_while_importing)

# the imports below take seconds: they run under the handler above
from absl import app, flags  # noqa: E402
from ml_collections.config_flags.config_flags import is_config_flag  # noqa: E402

from cvmdx_jax import cli_config, host_allocator  # noqa: E402
from cvmdx_jax.config.fields import ConfigFieldError  # noqa: E402
from cvmdx_jax.errors import UserError  # noqa: E402
from cvmdx_jax.models import performance  # noqa: E402
from cvmdx_jax.train import preemption  # noqa: E402

FLAGS = flags.FLAGS
USAGE_STATUS = 2
_PATH_ERRORS = (
    FileNotFoundError,
    NotADirectoryError,
    IsADirectoryError,
    FileExistsError,
    PermissionError,
)
_FULL = (errno.ENOSPC, errno.EDQUOT)
_MACHINE_ERRNOS = (*_FULL, errno.EROFS, errno.ENAMETOOLONG)
INTERRUPTED_STATUS = 130  # 128 + SIGINT, what a shell reports for Ctrl-C
TERMINATED_STATUS = 143  # 128 + SIGTERM


class Terminated(BaseException):
  """SIGTERM, raised in the main thread like KeyboardInterrupt for SIGINT."""


def _script() -> str:
  return Path(sys.argv[0]).stem


def fail(message: str) -> NoReturn:
  """Prints `<script>: error: <message>` (one line) to stderr and exits with status 2."""
  print(f"{_script()}: error: {' '.join(message.split())}", file=sys.stderr)
  sys.exit(USAGE_STATUS)


def is_user_error(exc: BaseException) -> bool:
  """True for the user errors of the module docstring."""
  return isinstance(exc, (app.UsageError, UserError, *_PATH_ERRORS))


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


_SIGNALLED: list[int] = []  # the signals received by this process (`_on_signal`)


def _on_signal(signum, frame) -> None:
  """Handler of SIGINT and SIGTERM: remembers the signal, raises in the main thread."""
  del frame
  _SIGNALLED.append(signum)
  raise KeyboardInterrupt if signum == signal.SIGINT else Terminated


def _stop(status: int, what: str) -> NoReturn:
  """Prints the signal's line and exits with `status`; after a real signal without the
  interpreter's exit handlers (module docstring)."""
  print(f"{_script()}: error: {what}; rerun to resume", file=sys.stderr)
  if not _SIGNALLED:  # raised in-process (a test): a plain exit
    sys.exit(status)
  sys.stdout.flush()
  sys.stderr.flush()
  os._exit(status)  # pylint: disable=protected-access


def _handle_signals() -> None:
  """Installs `_on_signal` for SIGINT (where not ignored) and SIGTERM."""
  if signal.getsignal(signal.SIGINT) is not signal.SIG_IGN:
    signal.signal(signal.SIGINT, _on_signal)
  signal.signal(signal.SIGTERM, _on_signal)


def run(main: Callable[[list[str]], object], *, allocator: bool = False) -> None:
  """`absl.app.run(main)` with the user-error handling of the module docstring; with
  `allocator` (the training entry points) in a process re-executed once with the
  allocator of `host_allocator` (Linux; not for `--help`). Both check their environment
  variables first (`models.performance`, `host_allocator`)."""
  try:
    performance.current()  # a bad CVMDX_WINOGRAD etc. is one line, before any work
    if allocator:
      host_allocator.reexec_with_allocator()
  except UserError as e:
    fail(str(e))

  def guarded(argv):
    try:
      return main(argv)
    except Exception as e:  # pylint: disable=broad-except
      message = str(e) if is_user_error(e) else machine_failure(e)
      if message is None:
        raise
      fail(message)

  _handle_signals()
  try:
    app.run(guarded, flags_parser=_parse_flags)
  except preemption.Stopped as e:  # training saved at a step boundary first
    _stop(e.code, e.message)
  except KeyboardInterrupt:
    _stop(INTERRUPTED_STATUS, "interrupted")
  except Terminated:
    _stop(TERMINATED_STATUS, "terminated")


def _reraise(error: Exception) -> NoReturn:
  raise error


def _parse_flags(argv: list[str]) -> list[str]:
  """`FLAGS(argv)` then the config checks; a user error exits via `fail`."""
  try:
    rest = FLAGS(argv)
  except flags.Error as e:
    fail(cli_config.flag_message(e))
  except (AttributeError, KeyError) as e:  # ml_collections: an override of no field
    name = cli_config.unknown_field(argv, e)
    if name is not None:
      fail(f"{name}: no such config field")
    fail(cli_config.load_failure(argv, e) or _reraise(e))
  except Exception as e:  # pylint: disable=broad-except
    fail(cli_config.load_failure(argv, e) or _reraise(e))
  for name in list(FLAGS):
    if is_config_flag(FLAGS[name]) and FLAGS[name].value is not None:
      problem = cli_config.check_config(name)
      if problem:
        fail(problem)
  for name, typed in _TYPED.items():
    typed.build(name)
  return rest


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
  flags (after the checks of `cli_config.check_config`); returns the holder of its result."""
  _TYPED[name] = TypedConfig(from_config)
  return _TYPED[name]


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


def int_list(name: str, low: int, high: int | None = None) -> None:
  """Validator: list flag `name` holds integers >= `low` (and <= `high`, where given)."""
  bound = f"in {low}..{high}" if high is not None else f">= {low}"
  top = float("inf") if high is None else high
  flags.register_validator(
      name,
      lambda v: all(re.fullmatch(r"-?\d+", s) and low <= int(s) <= top for s in v),
      f"expected integers {bound}, comma-separated",
  )
