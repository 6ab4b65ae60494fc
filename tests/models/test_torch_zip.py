"""Hostile `.pt` files: the reader bounds what it allocates by what the file holds, keeps
no state between reads, and refuses anything but plain containers and tensors with one
`TorchFileError` naming the file and the entry or tensor."""

import collections
import pickle
import re
import struct
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

from cvmdx_jax.models import torch_zip
from tests.models import official_fixture as fx
from tests.subprocess_env import pythonpath

REPO = Path(__file__).resolve().parents[2]


def _u(text: str) -> bytes:
  data = text.encode()
  return pickle.BINUNICODE + struct.pack("<I", len(data)) + data


def _global(module: str, name: str) -> bytes:
  return pickle.GLOBAL + f"{module}\n{name}\n".encode()


def _raw(path: Path, body: bytes, storages=None) -> Path:
  """A .pt file whose pickle is PROTO 2, `body`, STOP."""
  fx.write_archive(path, pickle.PROTO + b"\x02" + body + pickle.STOP, storages or {}, "a")
  return path


def _valid(tmp_path, monkeypatch):
  obj = {"w": np.arange(6, dtype=np.float32).reshape(2, 3), "n": np.array([1, 2], np.int64)}
  path = tmp_path / "valid.pt"
  fx.write_pt(path, obj, monkeypatch)
  return path, obj


def _check_valid(path, obj):
  got = torch_zip.read_pt(path)
  assert sorted(got) == sorted(obj)
  for k, v in obj.items():
    assert got[k].dtype == v.dtype and got[k].shape == v.shape
    np.testing.assert_array_equal(got[k], v)


STORAGE_RENAME = (
    _global("torch", "FloatStorage")
    + pickle.EMPTY_DICT
    + _u("name")
    + _u("HalfStorage")
    + pickle.SETITEM
    + pickle.BUILD
    + pickle.POP
    + pickle.EMPTY_DICT
)
SLOT_STATE = (
    _global("torch._utils", "_rebuild_tensor_v2")
    + pickle.NONE
    + pickle.EMPTY_DICT
    + _u("x")
    + pickle.BININT1
    + b"\x01"
    + pickle.SETITEM
    + pickle.TUPLE2
    + pickle.BUILD
    + pickle.POP
    + pickle.EMPTY_DICT
)
TYPE_STATE = (
    _global("collections", "OrderedDict")
    + pickle.EMPTY_DICT
    + _u("x")
    + pickle.NONE
    + pickle.SETITEM
    + pickle.BUILD
)


@pytest.mark.parametrize(
    "body, message",
    [
        (STORAGE_RENAME, "BUILD sets the state of torch.FloatStorage"),
        (SLOT_STATE, "BUILD sets the state of method"),
        (TYPE_STATE, "BUILD sets the state of type"),
    ],
)
def test_build_on_reader_objects_is_refused_and_leaves_no_state(
    tmp_path, monkeypatch, body, message
):
  path, obj = _valid(tmp_path, monkeypatch)
  _check_valid(path, obj)
  bad = _raw(tmp_path / "bad.pt", body)
  with pytest.raises(torch_zip.TorchFileError, match=f"bad.pt: {message}"):
    torch_zip.read_pt(bad)
  _check_valid(path, obj)  # still float32 of its own shape after the attack


def test_state_dict_metadata_is_read_and_dropped(tmp_path, monkeypatch):
  state = collections.OrderedDict(w=np.ones(3, np.float32))
  state._metadata = {"": {"version": 1}}  # what nn.Module.state_dict() attaches
  path = tmp_path / "sd.pt"
  fx.write_pt(path, state, monkeypatch)
  assert b"_metadata" in zipfile.ZipFile(path).read("archive/data.pkl")
  got = torch_zip.read_pt(path)
  assert type(got) is collections.OrderedDict and list(got) == ["w"]
  assert not hasattr(got, "_metadata")


def _tensor(base, offset, size, stride):
  return fx._Tensor("0", base, offset=offset, size=size, stride=stride)


@pytest.mark.parametrize(
    "offset, size, stride, base, message",
    [
        (0, (20000, 20000), (0, 0), 1, "broadcast, reversed or overlapping"),
        (2, (3,), (-1,), 3, "broadcast, reversed or overlapping"),
        (0, (3, 3), (1, 1), 9, "broadcast, reversed or overlapping"),
        (1, (4,), (1,), 4, "exceeds its storage of 4 elements"),
        (0, (2, 3), (4, 1), 6, "exceeds its storage of 6 elements"),
        (-1, (2,), (1,), 4, "offset -1 or size"),
        (0, (2**50,), (1,), 4, "out of range"),
        (0, (2.0,), (1,), 4, "must be an integer and two equally long tuples"),
        (0, (2, 2), (2,), 4, "must be an integer and two equally long tuples"),
    ],
)
def test_hostile_views_are_refused(tmp_path, monkeypatch, offset, size, stride, base, message):
  path = tmp_path / "views.pt"
  fx.write_pt(
      path, {"layer": {"w": _tensor(np.zeros(base, np.float32), offset, size, stride)}}, monkeypatch
  )
  with pytest.raises(torch_zip.TorchFileError) as e:
    torch_zip.read_pt(path)
  assert str(e.value).startswith(f"{path}: tensor layer.w (storage archive/data/0)")
  assert message in str(e.value) and "\n" not in str(e.value)


def test_views_torch_writes_are_read(tmp_path, monkeypatch):
  base = np.arange(24, dtype=np.float32)
  want = base.reshape(2, 3, 4).transpose(2, 0, 1)[1:, :, ::2]  # permuted, narrowed, stepped
  obj = {
      "perm": _tensor(base, 1, (3, 2, 2), (1, 12, 8)),
      "unit": _tensor(base, 5, (1, 3, 1), (0, 2, -7)),  # strides of size-1 dims are free
      "empty": _tensor(base, 0, (0, 5), (5, 1)),
  }
  path = tmp_path / "views.pt"
  fx.write_pt(path, obj, monkeypatch)
  got = torch_zip.read_pt(path)
  np.testing.assert_array_equal(got["perm"], want)
  np.testing.assert_array_equal(got["unit"], [[[5], [7], [9]]])
  assert got["empty"].shape == (0, 5) and got["empty"].dtype == np.float32


def test_views_sharing_a_storage_are_bounded(tmp_path, monkeypatch):
  base = np.zeros(4096, np.float32)
  path = tmp_path / "shared.pt"
  fx.write_pt(path, {f"v{i}": _tensor(base, 0, (4096,), (1,)) for i in range(20)}, monkeypatch)
  assert path.stat().st_size < 20_000  # 20 views of 16 kB: 320 kB of tensors
  with pytest.raises(torch_zip.TorchFileError, match="add up to more than twice the file"):
    torch_zip.read_pt(path)


def _archive(path, entries):
  """A zip of (name, bytes, compress_type) entries."""
  with zipfile.ZipFile(path, "w") as z:
    for name, data, method in entries:
      z.writestr(name, data, compress_type=method)
  return path


def test_zip_entries_are_checked_by_their_header(tmp_path, monkeypatch):
  pkl, storages = fx.pickled({"w": np.zeros(10, np.float32)}, monkeypatch)
  raw = storages["0"].tobytes()
  cases = {
      "deflated": (
          [("a/data.pkl", pkl, zipfile.ZIP_STORED), ("a/data/0", raw, zipfile.ZIP_DEFLATED)],
          "entry a/data/0 is compressed",
      ),
      "big pickle": (
          [("a/data.pkl", pickle.dumps("x" * (2 << 20), 2), zipfile.ZIP_STORED)],
          "entry a/data.pkl declares 2097162 bytes, more than the 524288 allowed",
      ),
      "short storage": (
          [("a/data.pkl", pkl, zipfile.ZIP_STORED), ("a/data/0", raw[:36], zipfile.ZIP_STORED)],
          "storage a/data/0 declares 10 elements of FloatStorage",
      ),
      "missing storage": (
          [("a/data.pkl", pkl, zipfile.ZIP_STORED)],
          "entry a/data/0 missing from the archive",
      ),
      "two pickles": (
          [("a/data.pkl", pkl, zipfile.ZIP_STORED), ("b/data.pkl", pkl, zipfile.ZIP_STORED)],
          "expected one <name>/data.pkl",
      ),
  }
  for name, (entries, message) in cases.items():
    path = _archive(tmp_path / f"{name}.pt", entries)
    with pytest.raises(torch_zip.TorchFileError) as e:
      torch_zip.read_pt(path)
    assert str(e.value).startswith(f"{path}: {message}"), (name, str(e.value))


@pytest.mark.parametrize("depth", [1, 8])
def test_entries_sharing_bytes_are_read_once_at_most(tmp_path, monkeypatch, depth):
  payload = np.arange(256, dtype=np.float32)
  pkl, _ = fx.pickled({f"t{k}": fx._Tensor(str(k), payload) for k in range(depth)}, monkeypatch)
  path = tmp_path / "nested.pt"
  fx.write_nested_entries(path, pkl, "a", payload.tobytes(), depth)
  with zipfile.ZipFile(path) as z:  # entries that share bytes, together larger than the file
    sizes = [z.getinfo(f"a/data/{k}").file_size for k in range(depth)]
    try:
      assert all(z.read(f"a/data/{k}")[-1024:] == payload.tobytes() for k in range(depth))
      message = f"the entries read add up to more than the archive's {path.stat().st_size} bytes"
    except zipfile.BadZipFile as e:  # newer CPython (3.12.3, not 3.12.1) refuses overlaps itself
      assert depth > 1 and "Overlapped entries" in str(e)
      message = "unreadable archive or pickle (BadZipFile: Overlapped entries"
  if depth == 1:
    np.testing.assert_array_equal(torch_zip.read_pt(path)["t0"], payload)
    return
  assert sum(sizes) > 3 * path.stat().st_size
  with pytest.raises(torch_zip.TorchFileError, match=re.escape(message)):
    torch_zip.read_pt(path)


NESTED = pickle.EMPTY_LIST * 40 + pickle.APPEND * 39


@pytest.mark.parametrize(
    "body, message",
    [
        (_global("collections", "OrderedDict") + pickle.EMPTY_TUPLE + pickle.NEWOBJ, "opcode"),
        (pickle.EXT1 + b"\x01", "opcode"),
        (pickle.EMPTY_SET, "opcode"),
        (pickle.MARK + _u("k") + pickle.NONE + pickle.DICT, "opcode"),
        (pickle.EMPTY_TUPLE + _u("k") + pickle.NONE + pickle.SETITEM, "SETITEM on tuple"),
        (pickle.EMPTY_DICT + pickle.NONE + pickle.APPEND, "APPEND on dict"),
        (
            pickle.EMPTY_DICT
            + pickle.EMPTY_TUPLE
            + pickle.TUPLE1 * 100_000
            + pickle.NONE
            + pickle.SETITEM,
            "a dict key of type tuple",
        ),
        (
            _global("torch", "FloatStorage") + pickle.EMPTY_TUPLE + pickle.REDUCE,
            "REDUCE calls torch.FloatStorage",
        ),
        (
            _global("collections", "OrderedDict")
            + pickle.EMPTY_LIST
            + pickle.TUPLE1
            + pickle.REDUCE,
            "REDUCE calls OrderedDict with arguments",
        ),
        (
            _global("builtins", "eval") + _u("1") + pickle.TUPLE1 + pickle.REDUCE,
            "names builtins.eval",
        ),
        (
            pickle.EMPTY_DICT + _u("k") + _global("torch", "FloatStorage") + pickle.SETITEM,
            "k: holds torch.FloatStorage",
        ),
        (
            pickle.EMPTY_LIST + pickle.BINPUT + b"\x00" + pickle.BINGET + b"\x00" + pickle.APPEND,
            "bad.pt: 0: containers nested deeper than 32 or in a cycle",
        ),
        (
            pickle.EMPTY_LIST + (pickle.EMPTY_LIST + pickle.APPEND) * 70_000,
            "65536: more than 65536 containers and tensors",
        ),
        (NESTED, "0.0.0.0.0.0.0.0.0.0.0.0.0.0.0.0.0.0.0.0.0.0.0.0.0.0.0.0.0.0.0.0: containers"),
        (
            _u("storage")
            + _global("torch", "FloatStorage")
            + _u("0")
            + pickle.BININT1
            + b"\x05"
            + pickle.TUPLE
            + pickle.BINPERSID,
            "unsupported persistent id",
        ),
    ],
)
def test_opcodes_and_containers_are_restricted(tmp_path, body, message):
  if body.startswith(_u("storage")):
    body = pickle.MARK + body
  path = _raw(tmp_path / "bad.pt", body)
  with pytest.raises(torch_zip.TorchFileError) as e:
    torch_zip.read_pt(path)
  assert str(e.value).startswith(f"{path}: ") and message in str(e.value), str(e.value)


# VmHWM, the peak RSS of this process image (ru_maxrss would include the forking parent's)
_MEASURE = """
import re, sys
from cvmdx_jax.models import torch_zip
peak = lambda: int(re.search(r"VmHWM:\\s+(\\d+) kB", open("/proc/self/status").read())[1])
before = peak()
try:
  torch_zip.read_pt(sys.argv[1])
  print("read")
except torch_zip.TorchFileError as e:
  print(e)
print((peak() - before) // 1024)
"""


def _peak_growth_mb(path) -> tuple[str, int]:
  done = subprocess.run(
      [sys.executable, "-c", _MEASURE, str(path)],
      cwd=REPO,
      check=True,
      env={"PYTHONPATH": pythonpath(), "PATH": "/usr/bin:/bin"},
      capture_output=True,
      text=True,
  )
  message, growth = done.stdout.strip().splitlines()
  return message, int(growth)


def test_tiny_files_declaring_huge_tensors_stay_small(tmp_path, monkeypatch):
  broadcast = tmp_path / "broadcast.pt"
  fx.write_pt(
      broadcast, {"w": _tensor(np.zeros(1, np.float32), 0, (20000, 20000), (0, 0))}, monkeypatch
  )
  bomb = tmp_path / "bomb.pt"
  numel = 2**30 // 4
  pkl, _ = fx.pickled(
      {"w": fx._Tensor("0", np.broadcast_to(np.float32(0), (numel,)), size=(numel,), stride=(1,))},
      monkeypatch,
  )
  fx.write_deflate_bomb(bomb, pkl, "archive", 2**30)
  with zipfile.ZipFile(bomb) as z:  # a real bomb: 1 GiB of zeros behind ~1 MB
    assert z.getinfo("archive/data/0").file_size == 2**30
    assert z.open("archive/data/0").read(1 << 20) == bytes(1 << 20)
  dicts = _raw(tmp_path / "dicts.pt", pickle.EMPTY_DICT * (torch_zip.MAX_PICKLE_BYTES - 4))
  assert broadcast.stat().st_size < 700 and bomb.stat().st_size < 1.1e6
  for path, message in (
      (broadcast, "broadcast, reversed or overlapping view"),
      (bomb, "entry archive/data/0 is compressed"),
      (dicts, "read"),
  ):  # the most Python objects a pickle makes
    text, growth = _peak_growth_mb(path)
    print(f"{path.name}: {path.stat().st_size} bytes, peak RSS growth {growth} MB: {text}")
    assert message in text and (text == "read" or text.startswith(str(path)))
    assert growth < (60 if path == dicts else 20), (path.name, growth)
