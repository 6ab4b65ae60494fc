"""Every JSON file the package writes is strict JSON: NaN and infinities become null, so
parsers that refuse Python's bare `NaN` / `Infinity` tokens (RFC 8259) read metrics.json."""

import json

import numpy as np
import pytest

from cvmdx_jax.storage import atomic


def _strict(text: str):
  def refuse(token):
    raise ValueError(f"non-standard JSON token {token}")

  return json.loads(text, parse_constant=refuse)


VALUE = {
    "ade": 1.5,
    "nll": float("nan"),
    "per_class": [float("inf"), 2.0, -float("inf")],
    "ece": np.float64("nan"),
    "nested": {"t": (float("nan"), 3)},
    "n": 7,
    "ok": True,
    "name": "NaN",
}
EXPECTED = {
    "ade": 1.5,
    "nll": None,
    "per_class": [None, 2.0, None],
    "ece": None,
    "nested": {"t": [None, 3]},
    "n": 7,
    "ok": True,
    "name": "NaN",
}


def test_write_json_writes_null_for_non_finite_floats(tmp_path):
  atomic.write_json(tmp_path / "metrics.json", VALUE)
  assert _strict((tmp_path / "metrics.json").read_text()) == EXPECTED


def test_json_lines_are_strict_too(tmp_path):
  atomic.write_jsonl(tmp_path / "log.jsonl", [VALUE, {"loss": float("nan")}])
  atomic.append_jsonl(tmp_path / "log.jsonl", {"loss": float("inf")})
  lines = (tmp_path / "log.jsonl").read_text().splitlines()
  assert [_strict(line) for line in lines] == [EXPECTED, {"loss": None}, {"loss": None}]


def test_the_reference_parser_refuses_what_json_dumps_writes_by_default():
  """The check of `_strict` can fail: Python's default output is not strict JSON."""
  with pytest.raises(ValueError, match="NaN"):
    _strict(json.dumps({"x": float("nan")}))
