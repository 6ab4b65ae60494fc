"""Shared helpers of the config files: the `:arg` string after a config path.

`--config=configs/x.py:tiny,q=60,quantizer=vq` calls `get_config("tiny,q=60,quantizer=vq")`;
`parse_arg` turns that into a ConfigDict against a spec of known keys and defaults.
"""

import ml_collections

from cvmdx_jax.errors import UserError

_TRUE = ("1", "true", "yes", "on")
_FALSE = ("0", "false", "no", "off")


def _cast(key: str, text: str, default):
  if isinstance(default, bool):
    low = text.lower()
    if low not in _TRUE + _FALSE:
      raise UserError(f"config arg '{key}={text}': expected a boolean")
    return low in _TRUE
  try:
    return type(default)(text)
  except ValueError as e:
    raise UserError(f"config arg '{key}={text}': expected {type(default).__name__}") from e


def parse_arg(arg: str | None, **spec) -> ml_collections.ConfigDict:
  """Parses a config arg such as "tiny" or "q=60,quantizer=vq".

  Args:
    arg: comma-separated items, each `key=value` or a bare `key` (meaning key=True,
      for boolean keys: presets). None or "" gives the defaults.
    **spec: every allowed key with its default; the default's type (bool, int, float,
      str) is the type the value is cast to.

  Returns:
    ConfigDict with one field per key of `spec`.

  Raises:
    ValueError: an unknown key, a bare non-boolean key, or a value of the wrong type.
  """
  out = dict(spec)
  for item in filter(None, (s.strip() for s in (arg or "").split(","))):
    key, sep, text = item.partition("=")
    key = key.strip()
    if key not in spec:
      raise UserError(f"config arg '{item}': unknown key '{key}', known: {sorted(spec)}")
    if not sep:
      if not isinstance(spec[key], bool):
        raise UserError(f"config arg '{item}': '{key}' needs a value ({key}=...)")
      out[key] = True
    else:
      out[key] = _cast(key, text.strip(), spec[key])
  return ml_collections.ConfigDict(out)
