"""`cvmdx_jax.storage.atomic`: all-or-nothing writes, umask-respecting modes, format round trips."""

import contextlib
import errno
import json
import os
import stat
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import scipy.io

from cvmdx_jax.runs import tokens
from cvmdx_jax.storage import atomic


class _Boom:
  """Fails when a writer converts it to an array, i.e. after earlier entries are written."""

  def __array__(self, *args, **kwargs):
    raise RuntimeError("boom")


FAILING_WRITERS = {
    "writing": lambda p: _write_then_fail(p),
    "npz": lambda p: atomic.write_npz(p, a=np.ones(1000), b=_Boom()),
    "mat": lambda p: atomic.write_mat(p, {"a": np.ones(1000), "b": _Boom()}),
    "jsonl": lambda p: atomic.write_jsonl(p, ({"i": i} if i < 3 else 1 / 0 for i in range(5))),
}


def _write_then_fail(path):
  with atomic.writing(path) as f:
    f.write(b"new and partial")
    f.flush()
    raise RuntimeError("boom")


@pytest.mark.parametrize("name", sorted(FAILING_WRITERS))
def test_failing_writer_keeps_old_file_and_leaves_no_temporary(tmp_path, name):
  target = tmp_path / f"out.{name}"
  target.write_bytes(b"old content")
  with pytest.raises((RuntimeError, ZeroDivisionError)):
    FAILING_WRITERS[name](target)
  assert target.read_bytes() == b"old content"
  assert sorted(p.name for p in tmp_path.iterdir()) == [target.name]


@pytest.mark.parametrize("umask", [0o022, 0o027, 0o077, 0o002])
def test_mode_is_what_plain_open_creates(tmp_path, umask):
  old = os.umask(umask)
  try:
    with open(tmp_path / "plain", "w") as f:
      f.write("x")
    atomic.write_text(tmp_path / "a.txt", "x")
    atomic.append_jsonl(tmp_path / "log.jsonl", {"epoch": 1})
    tokens.save_tokens(
        tmp_path / "tokens" / "test.npz",
        tokens.Tokens(
            q=np.zeros(2, np.int32),
            z_hat=np.zeros((2, 3), np.float32),
            delta=np.zeros(2, np.float32),
        ),
        {"dataset_id": "x"},
    )
  finally:
    os.umask(old)
  want = 0o666 & ~umask
  assert stat.S_IMODE((tmp_path / "plain").stat().st_mode) == want
  for name in ("a.txt", "log.jsonl", "tokens/test.npz"):
    assert stat.S_IMODE((tmp_path / name).stat().st_mode) == want, name
  if umask == 0o022:
    assert want == 0o644


def test_bytes_text_json_round_trip(tmp_path):
  atomic.write_bytes(tmp_path / "b", b"\x00\xff")
  atomic.write_text(tmp_path / "t", "ä\nb")
  atomic.write_json(tmp_path / "j", {"a": [1, 2.5, None]}, sort_keys=True)
  assert (tmp_path / "b").read_bytes() == b"\x00\xff"
  assert (tmp_path / "t").read_text(encoding="utf-8") == "ä\nb"
  assert (tmp_path / "j").read_text() == '{\n  "a": [\n    1,\n    2.5,\n    null\n  ]\n}\n'


def test_jsonl_rewrite_and_append(tmp_path):
  path = tmp_path / "metrics.jsonl"
  atomic.write_jsonl(path, [{"epoch": 1, "loss": 0.5}, {"epoch": 2, "loss": float("nan")}])
  before = path.read_bytes()
  atomic.append_jsonl(path, {"epoch": 3, "loss": 0.25})
  assert path.read_bytes().startswith(before)
  lines = path.read_text().splitlines()
  assert [json.loads(x)["epoch"] for x in lines] == [1, 2, 3]
  assert lines[0] == '{"epoch": 1, "loss": 0.5}'
  atomic.write_jsonl(path, [])
  assert path.read_bytes() == b""


def test_npz_and_mat_round_trip(tmp_path):
  a = np.arange(12, dtype=np.float32).reshape(3, 4)
  b = np.array([True, False])
  atomic.write_npz(tmp_path / "x.npz", a=a, b=b)
  with np.load(tmp_path / "x.npz") as data:
    np.testing.assert_array_equal(data["a"], a)
    np.testing.assert_array_equal(data["b"], b)
    assert data["a"].dtype == np.float32
  atomic.write_mat(tmp_path / "x.mat", {"a": a.astype(np.float64), "s": np.array(["kl"])})
  mat = scipy.io.loadmat(tmp_path / "x.mat")
  np.testing.assert_array_equal(mat["a"], a)
  assert str(mat["s"][0]) == "kl"


def test_csv(tmp_path):
  frame = pd.DataFrame({"id": [1, 2], "x": [0.125, 3.0]})
  with atomic.writing(tmp_path / "t.csv", "w") as f:
    frame.to_csv(f, index=False, float_format="%.2f")
  assert (tmp_path / "t.csv").read_text() == "id,x\n1,0.12\n2,3.00\n"
  assert sorted(p.name for p in tmp_path.iterdir()) == ["t.csv"]


class _FullDisk:
  """A file whose writes fail like a full disk."""

  def write(self, data):
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

  def flush(self):
    pass


def test_write_all_is_all_or_nothing(tmp_path, monkeypatch):
  names = ("metrics.json", "a.png", "b.png")
  for name in names:
    (tmp_path / name).write_bytes(b"old " + name.encode())
  real = atomic.writing

  @contextlib.contextmanager
  def full_at_b(path, mode="wb"):
    with real(path, mode) as f:
      yield _FullDisk() if Path(path).name == "b.png" else f

  files = {tmp_path / name: b"new " + name.encode() for name in names}
  monkeypatch.setattr(atomic, "writing", full_at_b)
  with pytest.raises(OSError, match="No space left"):
    atomic.write_all(files)
  assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == {
      name: b"old " + name.encode() for name in names
  }  # no temporary either
  monkeypatch.setattr(atomic, "writing", real)
  renamed = []
  replace = os.replace
  monkeypatch.setattr(
      atomic.os, "replace", lambda a, b: (renamed.append(Path(b).name), replace(a, b))
  )
  atomic.write_all(files)
  assert renamed == ["b.png", "a.png", "metrics.json"]  # the first one last
  assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == {
      name: b"new " + name.encode() for name in names
  }


def test_writing_rejects_other_modes(tmp_path):
  with pytest.raises(ValueError, match="mode='a'"):
    with atomic.writing(tmp_path / "x", "a"):
      pass
