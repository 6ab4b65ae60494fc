"""The one runner of the absl entry points in `experiments/`: `run(main)`.

A user's mistake ends the same way in every script: one line
`<script>: error: <message>` on stderr naming the flag, file or field, exit status 2,
no traceback. User errors are
- flag errors, found before `main` starts: an unknown flag, a value of the wrong type
  or out of range (`lower_bound=`, validators), a required flag left out, an unknown
  config preset or field, a config file that cannot be loaded, a config field out of
  range (`CONFIG_RANGES`), a `*_dir` config field that is not a directory;
- in `main`: `app.UsageError` (stray arguments), a `ValueError` raised by this
  repository's code (`DataError`, `IncompatibleRunsError`, `CheckpointMismatchError`,
  `WorkdirLockedError`, ...: their messages name the file or field) and a missing or
  unwritable path (`FileNotFoundError`, `NotADirectoryError`, `PermissionError`, ...).
Anything else keeps its traceback, also a ValueError raised inside a library (a bad
array handed to numpy or JAX is a bug of ours, not of the user).

Validators for plain flags: `input_dirs`, `output_dirs`, `presets`, `int_list`.
"""

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

FLAGS = flags.FLAGS
USAGE_STATUS = 2
_REPO = Path(__file__).resolve().parents[1]
_OUR_CODE = ("cvmdx_jax", "configs", "experiments")
_PATH_ERRORS = (FileNotFoundError, NotADirectoryError, IsADirectoryError, FileExistsError,
                PermissionError)


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


def run(main: Callable[[list[str]], object]) -> None:
  """`absl.app.run(main)` with the user-error handling of the module docstring, in a
  process re-executed once with the allocator of `host_allocator` (Linux)."""
  try:
    host_allocator.reexec_with_allocator()
  except ValueError as e:
    fail(str(e))

  def guarded(argv):
    try:
      return main(argv)
    except Exception as e:  # pylint: disable=broad-except
      if not is_user_error(e):
        raise
      fail(str(e))

  app.run(guarded, flags_parser=_parse_flags)


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
  return rest


# ------------------------------------------------------------- config fields


def _positive(v) -> bool:
  return v > 0


def _non_negative(v) -> bool:
  return v >= 0


def _fraction(v) -> bool:
  return 0 <= v <= 1


def _below_one(v) -> bool:
  return 0 <= v < 1


def _seed(v) -> bool:
  return 0 <= v < 2**32  # jax.random.key wraps larger seeds


_RULES = {_positive: "> 0", _non_negative: ">= 0", _fraction: "in [0, 1]",
          _below_one: "in [0, 1)", _seed: "in [0, 2**32)"}
# Ranges of the numeric fields of configs/*.py that the scripts read (a tuple field: each
# element); a field a config does not have is skipped. Every float must also be finite.
CONFIG_RANGES = {
    # configs/tokenizer.py
    "encode_batch": _positive, "model.encoder.latent_dim": _positive,
    "model.encoder.channels": _positive, "model.encoder.kernel_size": _positive,
    "model.cls_weight": _non_negative, "model.ego_weight": _non_negative,
    "quantizer.codebook_size": _positive, "quantizer.beta": _non_negative,
    "quantizer.usage_decay": _fraction, "quantizer.revive_strength": _non_negative,
    "uncertainty.shrinkage": _non_negative, "uncertainty.ridge": _non_negative,
    # configs/tokenizer.py and configs/diffusion.py
    "seed": _seed, "train.batch_size": _positive, "train.num_epochs": _positive,
    "train.learning_rate": _positive, "train.grad_clip": _non_negative,
    "train.checkpoint_every": _positive, "train.keep": _positive,
    # configs/diffusion.py
    "model.base_channels": _positive, "model.channel_mult": _positive,
    "model.num_res_blocks": _positive, "model.emb_mult": _positive,
    "model.num_heads": _positive, "model.groups": _positive, "model.dropout": _below_one,
    "model.attention_levels": _non_negative,
    "diffusion.num_steps": _positive, "diffusion.cond_drop_prob": _below_one,
    "diffusion.control_scale": _positive, "diffusion.residual_decay_s": _positive,
    "train.warmup_steps": _non_negative, "train.min_lr": _non_negative,
    "train.weight_decay": _non_negative, "train.ema_decay": _below_one,
    "sampling.num_samples": _positive, "sampling.steps": _positive,
    "sampling.eta": _non_negative, "sampling.clip_x0": _non_negative,
    "sampling.guidance.w_min": _non_negative, "sampling.guidance.w_max_base": _non_negative,
    "sampling.guidance.t_c": _positive, "sampling.hypotheses.c_max": _positive,
    "sampling.hypotheses.x_scale": _positive, "sampling.hypotheses.y_scale": _positive,
    "sampling.hypotheses.pca_dim": _positive, "sampling.hypotheses.reg_covar": _positive,
    "sampling.hypotheses.em_iters": _positive,
    # configs/baseline.py
    "model.num_hypotheses": _positive, "model.token_dim": _positive, "model.hidden": _positive,
    "model.control_scale": _positive, "model.residual_decay_s": _positive,
    "loss.cls_weight": _non_negative, "train.end_lr_fraction": _fraction,
    # configs/dataset.py
    "mat_val_fraction": _below_one, "extraction.seed": _seed, "splits.train": _positive,
    "splits.val": _positive, "splits.test": _positive, "splits.test_ood": _positive,
    "extraction.lc_offsets_s": _positive, "extraction.kl_stride_s": _positive,
    "extraction.control_smoothing": _non_negative, "extraction.control_iterations": _positive,
    "sumo.seed": _seed, "sumo.recordings.train": _positive,
    "sumo.recordings.val": _positive, "sumo.recordings.test": _positive,
    "sumo.recordings.test_ood": _non_negative, "sumo.workers": _positive,
    "sumo.warmup_s": _non_negative, "sumo.duration_s": _positive,
    "sumo.road_length_m": _positive, "sumo.section_length_m": _positive,
    "sumo.lanes": _positive, "sumo.lane_width_m": _positive,
    "sumo.speed_limits_kmh": _positive, "sumo.flow_per_lane": _positive,
    "sumo.truck_share": _fraction, "sumo.car_types": _positive, "sumo.truck_types": _positive,
    "sumo.held_out.lanes": _positive, "sumo.held_out.duration_s": _positive,
}


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
  rule = CONFIG_RANGES.get(path)
  if rule is not None and not all(rule(v) for v in values if _is_number(v)):
    return f"must be {_RULES[rule]}"
  return None


def _dir_problem(path: str, value) -> str | None:
  """A non-empty `*_dir` field must name a directory (they are all inputs)."""
  if path.rsplit(".", 1)[-1].endswith("_dir") and isinstance(value, str) and value:
    if not Path(value).is_dir():
      return "no such directory"
  return None


def check_config(name: str) -> str | None:
  """The first problem of config flag `--name` (load failure, a field's type or range, a
  `*_dir` field that is not a directory) as a message naming the field; None if none."""
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


def input_dirs(*names: str) -> None:
  """Validators: each flag of `names`, when set, names an existing directory."""
  for name in names:
    flags.register_validator(name, lambda v: v is None or Path(v).is_dir(),
                             "no such directory")


def output_dirs(*names: str) -> None:
  """Validators: each flag of `names`, when set, is a directory that can be written or
  created (`writable`)."""
  for name in names:
    flags.register_validator(name, lambda v: v is None or writable(v),
                             "cannot create or write a directory there")


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
