"""Identity of stored things: the one content id, the one JSON normalisation and the one
"belongs together" check.

`content_id(value)` is the sha256 hex of nested dicts / lists / tuples of JSON scalars and
arrays (leaf paths, dtypes, shapes and bytes): the id of a dataset cache (`data.cache`),
of given splits and of a checkpoint's parameters (`train.tokenizer`). `to_json` turns a
value into plain JSON data (tuples become lists). `check(saved, expected, what, error)`
raises `error` naming every dotted key where two fingerprints differ; it is used by resume
(`train.loop`), the tokeniser run and the loaders (`runs.loaders`), the pairing of a
denoiser with a tokeniser (`inference.predictor`), the saved tokens (`runs.tokens`) and
the dataset cache (`data.cache`, via `differing_keys`).
"""

import hashlib
import json
from typing import Any

import jax
import numpy as np


def to_json(value: Any, name: str = "fingerprint") -> Any:
  """`value` as plain JSON data (tuples become lists); ValueError when it is not JSON-able."""
  try:
    return json.loads(json.dumps(value, sort_keys=True))
  except (TypeError, ValueError) as e:
    raise ValueError(f"{name} must be JSON-serialisable: {e}") from e


def _leaf_bytes(x: Any) -> bytes:
  if isinstance(x, jax.Array) and not x.is_fully_addressable:
    x = x.addressable_data(0)  # replicated train state: every process holds all of it
  return np.ascontiguousarray(jax.device_get(x)).tobytes()


def _leaves(value: Any, path: str = ""):
  """(path "/a/0/b", leaf) of nested dicts (sorted keys), lists and (named) tuples."""
  if isinstance(value, dict):
    for k in sorted(value, key=str):
      yield from _leaves(value[k], f"{path}/{k}")
  elif isinstance(value, (list, tuple)) and not hasattr(value, "dtype"):
    names = getattr(value, "_fields", range(len(value)))
    for k, v in zip(names, value):
      yield from _leaves(v, f"{path}/{k}")
  else:
    yield path, value


def _is_array(leaf: Any) -> bool:
  return hasattr(leaf, "dtype") and hasattr(leaf, "shape")


def content_id(value: Any) -> str:
  """sha256 hex of `value`: nested dicts / lists / tuples of JSON scalars and arrays.

  Plain JSON data hash as their canonical text (`json.dumps(value, sort_keys=True)`);
  with arrays, each leaf contributes its path, and for an array its dtype, shape and bytes.
  """
  leaves = list(_leaves(value))
  if not any(_is_array(leaf) for _, leaf in leaves):
    return hashlib.sha256(json.dumps(value, sort_keys=True).encode()).hexdigest()
  digest = hashlib.sha256()
  for path, leaf in leaves:
    if _is_array(leaf):
      digest.update(f"{path}:{np.dtype(leaf.dtype).name}:{tuple(leaf.shape)};".encode())
      digest.update(_leaf_bytes(leaf))
    else:
      digest.update(f"{path}={json.dumps(leaf)};".encode())
  return digest.hexdigest()


def _flatten(value: Any, prefix: str = "") -> dict[str, Any]:
  if isinstance(value, dict) and value:
    out = {}
    for k, v in value.items():
      out.update(_flatten(v, f"{prefix}.{k}" if prefix else str(k)))
    return out
  return {prefix: value}


def differing_keys(
    saved: Any, expected: Any, names: tuple[str, str] = ("saved", "expected")
) -> list[str]:
  """The dotted keys where `saved` and `expected` (JSON-able) differ, each as
  "key: saved X, expected Y" (`names` replaces the two words); empty when they are equal
  after JSON normalisation."""
  a, b = _flatten(to_json(saved)), _flatten(to_json(expected))
  return [
      f"{k}: {names[0]} {a.get(k, '<absent>')!r}, {names[1]} {b.get(k, '<absent>')!r}"
      for k in sorted(set(a) | set(b))
      if a.get(k, KeyError) != b.get(k, KeyError)
  ]


def check(saved: Any, expected: Any, what: str, error: type[Exception] = ValueError) -> None:
  """Raises `error` naming every differing key when `saved` does not equal `expected`.

  Args:
    saved: the fingerprint found (in a checkpoint, a file's metadata, ...).
    expected: the fingerprint it must have.
    what: what was found, for the message ("checkpoint runs/x/checkpoints/5").
    error: the exception class raised.
  """
  diffs = differing_keys(saved, expected)
  if diffs:
    raise error(f"{what} belongs to another run; differing keys: " + "; ".join(diffs))
