"""One conversion from config sections (ConfigDict or JSON dicts) to frozen dataclasses.

    unet = to_dataclass(UNetConfig, config.model, num_tokens=q)
    sampling = to_dataclass(SamplingConfig, config.sampling, clip_x0=None)

Fields whose type is a dataclass are built from the nested section; lists become tuples
(so the result is hashable and usable as a static jit argument); fields the section
leaves out keep the dataclass defaults. The dataclass's own checks (`__post_init__`)
run as usual.
"""

import dataclasses
import typing
from collections.abc import Mapping
from typing import Any, TypeVar

T = TypeVar("T")


def _is_section(value: Any) -> bool:
  return isinstance(value, Mapping) or hasattr(value, "to_dict")  # dict or ConfigDict


def _freeze(value: Any) -> Any:
  if isinstance(value, (list, tuple)):
    return tuple(_freeze(v) for v in value)
  return value


def to_dataclass(cls: type[T], section: Any, **overrides) -> T:
  """Builds dataclass `cls` from `section` (a ConfigDict or dict), then `overrides`.

  Raises:
    ValueError: `section` holds a key that is not a field of `cls` (names the key).
  """
  items = dict(section.items())
  items.update(overrides)
  fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
  unknown = sorted(set(items) - set(fields))
  if unknown:
    raise ValueError(f"{cls.__name__}: unknown field(s) {unknown}; known: {sorted(fields)}")
  hints = typing.get_type_hints(cls)
  kwargs = {}
  for name, value in items.items():
    kind = hints[name]
    if dataclasses.is_dataclass(kind) and _is_section(value):
      kwargs[name] = to_dataclass(kind, value)
    else:
      kwargs[name] = _freeze(value)
  return cls(**kwargs)
