"""Per-backend performance paths of the U-Net: which implementation a layer traces.

Two layers have a fast path written for XLA:CPU beside XLA's plain one:
- `winograd`: `winograd.conv3` by Winograd's F(4, 3) where both channel counts are >= 128
  (plain: `lax.conv_general_dilated`);
- `group_norm_backward`: `group_norm.GroupNorm` through the custom_vjp functions with the
  hand-written backward pass, the (B, C) coefficients and the 0/1-matrix expansion
  (plain: GroupNorm by reshape to groups and autodiff, as `flax.nnx.GroupNorm`).
Both compute the same function to float32 rounding; parameters, checkpoints and configs
do not depend on the choice.

Each option is "auto", "on" or "off". "auto" (the default) is the fast path on the CPU
backend and the plain path on every other one, the choice measured (BUILD_NOTES.md,
"Performance paths per backend"): it is staged out with `jax.lax.platform_dependent`, so
both paths are traced and the one for the platform a function is lowered for is the only
one compiled; on CPU the compiled program is the same as with "on" (bit-identical results,
tests/models/test_performance.py). "on" and "off" trace one path only.

Set for the process by the environment, read once at the first trace:
`CVMDX_WINOGRAD`, `CVMDX_GROUP_NORM_BACKWARD` = auto | on | off (empty: auto; any other
value is a `ValueError` naming the variable, which `cli.run` reports before any work).
In code, `with performance.use(PerformanceOptions(...)):` sets them for a block (tests,
experiments/benchmark.py). Options are read when a function is traced: a jitted function
keeps the path of its first trace, so `use` clears JAX's in-memory caches when it changes
the options (the persistent compilation cache keys on the program and stays valid).
"""

import contextlib
import dataclasses
import functools
import os
from collections.abc import Callable, Iterator, Mapping

import jax

from cvmdx_jax.errors import UserError

CHOICES = ("auto", "on", "off")
ENVIRONMENT = {"winograd": "CVMDX_WINOGRAD", "group_norm_backward": "CVMDX_GROUP_NORM_BACKWARD"}
FAST_PLATFORM = "cpu"  # where "auto" takes the fast paths


def _check(value: str, name: str) -> None:
  if value not in CHOICES:
    raise UserError(f"{name}={value!r}: expected one of {', '.join(CHOICES)}")


@dataclasses.dataclass(frozen=True)
class PerformanceOptions:
  """Which path each option traces: "auto" (fast on CPU, plain elsewhere), "on", "off"."""

  winograd: str = "auto"
  group_norm_backward: str = "auto"

  def __post_init__(self):
    for field in dataclasses.fields(self):
      _check(getattr(self, field.name), field.name)

  def resolved(self, platform: str) -> dict[str, bool]:
    """{option: whether the fast path runs} for a backend `platform` ("cpu", "gpu", ...)."""
    return {
        name: value == "on" or (value == "auto" and platform == FAST_PLATFORM)
        for name, value in dataclasses.asdict(self).items()
    }

  def describe(self, platform: str) -> str:
    """One line, e.g. "winograd=auto (on), group_norm_backward=off (off)" on `platform`."""
    fast = self.resolved(platform)
    return ", ".join(
        f"{name}={value} ({'on' if fast[name] else 'off'})"
        for name, value in dataclasses.asdict(self).items()
    )


def from_environment(environ: Mapping[str, str]) -> PerformanceOptions:
  """The options of `ENVIRONMENT`'s variables in `environ` (unset or empty: "auto").

  Raises:
    ValueError: a variable holds another value (names the variable).
  """
  values = {}
  for name, variable in ENVIRONMENT.items():
    values[name] = environ.get(variable, "") or "auto"
    _check(values[name], variable)
  return PerformanceOptions(**values)


@functools.cache
def _process_options() -> PerformanceOptions:
  return from_environment(os.environ)


_override: list[PerformanceOptions] = []  # innermost `use` last


def current() -> PerformanceOptions:
  """The options in force: the innermost `use`, else the process's environment."""
  return _override[-1] if _override else _process_options()


@contextlib.contextmanager
def use(options: PerformanceOptions) -> Iterator[PerformanceOptions]:
  """Traces with `options` inside the block; clears JAX's caches where that changes them
  (on entry and exit), so no function keeps a path traced with other options."""
  before = current()
  if options != before:
    jax.clear_caches()
  _override.append(options)
  try:
    yield options
  finally:
    _override.pop()
    if options != before:
      jax.clear_caches()


def select(option: str, fast: Callable, plain: Callable, *args):
  """fast(*args) or plain(*args) as option `option` of `current()` says; "auto":
  `lax.platform_dependent` (fast on CPU, plain on other platforms). `args` are arrays;
  close over static arguments."""
  value = getattr(current(), option)
  if value == "on":
    return fast(*args)
  if value == "off":
    return plain(*args)
  return jax.lax.platform_dependent(*args, default=plain, **{FAST_PLATFORM: fast})
