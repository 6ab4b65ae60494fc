"""Typed configs: one conversion from config sections to frozen dataclasses, and the
field ranges those dataclasses check.

    unet = to_dataclass(UNetConfig, config.model, num_tokens=q)
    sampling = to_dataclass(SamplingConfig, config.sampling, where="sampling")

Fields whose type is a dataclass are built from the nested section; lists become tuples
(so the result is hashable and usable as a static jit argument); fields the section
leaves out keep the dataclass defaults. Each dataclass checks its own fields in
`__post_init__`, numeric ones with `check_ranges(self, {field: POSITIVE, ...})`; a
failure is a `ConfigFieldError` whose `field` is the dotted path in the config
(`to_dataclass` prefixes the section, e.g. "diffusion.class_weights"), which the entry
points (`cvmdx_jax.cli`) print as `--config.<field>=<value>: <problem>`.
"""

import dataclasses
import math
import numbers
import typing
from collections.abc import Callable, Mapping
from typing import Any, TypeVar

from cvmdx_jax.errors import UserError

T = TypeVar("T")


class ConfigFieldError(UserError):
  """A config field with a value out of its range; `field` is its dotted config path."""

  def __init__(self, field: str, value: Any, problem: str):
    self.field, self.value, self.problem = field, value, problem
    super().__init__(f"{field}={value}: {problem}")

  def within(self, section: str) -> "ConfigFieldError":
    """The same error for the field seen from the enclosing `section`."""
    return ConfigFieldError(f"{section}.{self.field}", self.value, self.problem)


@dataclasses.dataclass(frozen=True)
class Range:
  """A range rule of a numeric field (each element of a tuple field)."""

  text: str
  test: Callable[[float], bool]


POSITIVE = Range("> 0", lambda v: v > 0)
NON_NEGATIVE = Range(">= 0", lambda v: v >= 0)
FRACTION = Range("in [0, 1]", lambda v: 0 <= v <= 1)
BELOW_ONE = Range("in [0, 1)", lambda v: 0 <= v < 1)
AT_LEAST_TWO = Range(">= 2", lambda v: v >= 2)
SEED = Range("in [0, 2**32)", lambda v: 0 <= v < 2**32)  # jax.random.key wraps larger seeds


def _is_number(v) -> bool:
  return isinstance(v, (int, float)) and not isinstance(v, bool)


def check_ranges(obj: Any, ranges: Mapping[str, Range]) -> None:
  """Raises ConfigFieldError for the first field of `obj` named in `ranges` that is not
  a finite number (or tuple of them) inside its range; None values are skipped."""
  for name, rule in ranges.items():
    value = getattr(obj, name)
    if value is None:
      continue
    values = value if isinstance(value, tuple) else (value,)
    if not all(map(_is_number, values)):
      raise ConfigFieldError(name, value, "expected a number or a tuple of numbers")
    if not all(math.isfinite(v) for v in values):
      raise ConfigFieldError(name, value, "must be finite")
    if not all(rule.test(v) for v in values):
      raise ConfigFieldError(name, value, f"must be {rule.text}")


def check_integers(obj: Any, names: tuple[str, ...]) -> None:
  """Makes each field of `names` a plain int (a numpy integer or a whole float such as
  9.0 is accepted); ConfigFieldError for one that is not a whole number (9.5, "9", True)."""
  for name in names:
    value = getattr(obj, name)
    whole = isinstance(value, numbers.Integral) or (
        isinstance(value, float) and math.isfinite(value) and value == int(value)
    )
    if isinstance(value, bool) or not whole:
      raise ConfigFieldError(name, value, "must be a whole number")
    object.__setattr__(obj, name, int(value))


def _is_section(value: Any) -> bool:
  return isinstance(value, Mapping) or hasattr(value, "to_dict")  # dict or ConfigDict


def _freeze(value: Any) -> Any:
  if isinstance(value, (list, tuple)):
    return tuple(_freeze(v) for v in value)
  return value


def to_dataclass(cls: type[T], section: Any, *, where: str = "", **overrides) -> T:
  """Builds dataclass `cls` from `section` (a ConfigDict or dict), then `overrides`.

  Args:
    cls: a dataclass; fields typed as dataclasses are built from nested sections.
    section: the config section.
    where: the section's dotted path in the config, for error messages ("" = the root).
    **overrides: field values set instead of the section's.

  Raises:
    ConfigFieldError: a field out of range (its `field` names the full dotted path).
    ValueError: `section` holds a key that is not a field of `cls`, or another check of
      `cls` failed (the message names the section).
  """
  items = dict(section.items())
  items.update(overrides)
  fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
  unknown = sorted(set(items) - set(fields))
  if unknown:
    raise UserError(
        f"{where or cls.__name__}: unknown field(s) {unknown}; known: " f"{sorted(fields)}"
    )
  hints = typing.get_type_hints(cls)
  kwargs = {}
  for name, value in items.items():
    kind = hints[name]
    if dataclasses.is_dataclass(kind) and _is_section(value):
      kwargs[name] = to_dataclass(kind, value, where=f"{where}.{name}" if where else name)
    else:
      kwargs[name] = _freeze(value)
  try:
    return cls(**kwargs)
  except ConfigFieldError as e:
    raise (e.within(where) if where else e) from None
  except ValueError as e:
    if not where or str(e).startswith(where):
      raise
    raise UserError(f"{where}: {e}") from None
