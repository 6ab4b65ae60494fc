"""Seeded random corruption of a valid `.pt` file: `read_pt` either reads it correctly or
raises one `TorchFileError` whose one-line message starts with the file's name; never
another exception, and never more memory (tracemalloc peak) than a bound linear in the
file's length.

Each case writes one file and states what a read must give: (READ, obj) (must equal
obj), (MAYBE, obj) (equal obj or raise), (REFUSE, None) (must raise) or (ANY, None)
(raise, or return a tree of plain containers, scalars and arrays no larger than twice the
file).
"""

import collections
import math
import pickletools
import struct
import tracemalloc

import numpy as np
import pytest

from cvmdx_jax.models import torch_tensors, torch_zip
from tests.models import official_fixture as fx

READ, MAYBE, REFUSE, ANY = "read", "maybe", "refuse", "any"
OPCODES = bytes(op.code.encode("latin-1")[0] for op in pickletools.opcodes)  # all of them
NAME = "archive"


def _clean():
  base = np.arange(24, dtype=np.float32)
  return {
      "model": collections.OrderedDict(
          [
              ("conv.weight", np.linspace(-1, 1, 12, dtype=np.float32).reshape(4, 1, 3)),
              ("conv.bias", np.array([0.5, -2.0, 3.0, 1e-3], np.float32)),
              ("steps", np.array([3, -1, 2**40], np.int64)),
          ]
      ),
      "view": fx._Tensor("v", base, offset=1, size=(2, 3), stride=(1, 4)),
      "meta": {"step": 5, "names": ["a", "b"], "pair": (1.5, None)},
  }


def _expected(obj):
  """The object a read of `obj` (as `fx.pickled` takes it) must give."""
  if isinstance(obj, fx._Tensor):
    return _gather(obj.array, obj.offset, obj.size, obj.stride)
  if isinstance(obj, dict):
    return type(obj)((k, _expected(v)) for k, v in obj.items())
  if type(obj) in (list, tuple):
    return type(obj)(map(_expected, obj))
  return obj


def _flat(offset, size, stride) -> np.ndarray:
  """The storage index of each element of a view: offset + idx . stride, shape `size`."""
  return np.asarray(offset + sum(i * s for i, s in zip(np.indices(size), stride)), np.int64)


def _gather(base, offset, size, stride):
  return np.asarray(base[_flat(offset, size, stride)])


def _equal(got, want) -> bool:
  if isinstance(want, np.ndarray):
    return (
        isinstance(got, np.ndarray)
        and got.dtype == want.dtype
        and got.shape == want.shape
        and np.array_equal(got, want)
    )
  if type(got) is not type(want):
    return False
  if isinstance(want, dict):
    return list(got) == list(want) and all(_equal(got[k], want[k]) for k in want)
  if isinstance(want, (list, tuple)):
    return len(got) == len(want) and all(map(_equal, got, want))
  return got == want


def _plain(obj, depth=0) -> int:
  """Bytes of the arrays in a tree of plain values (AssertionError if it is not one)."""
  assert depth < torch_tensors.MAX_DEPTH
  if isinstance(obj, np.ndarray):
    return obj.nbytes
  if isinstance(obj, dict):
    assert all(isinstance(k, (str, bytes, int, float, type(None))) for k in obj)
    return sum(_plain(v, depth + 1) for v in obj.values())
  if type(obj) in (list, tuple):
    return sum(_plain(v, depth + 1) for v in obj)
  assert isinstance(obj, (str, bytes, int, float, type(None))), type(obj)
  return 0


def _central_records(data: bytes) -> list[int]:
  """Offsets of the central-directory records of a zip file."""
  out, i = [], data.find(b"PK\x01\x02")
  while i >= 0:
    out.append(i)
    i = data.find(b"PK\x01\x02", i + 4)
  return out


def _mutate_bytes(rng, data: bytes, kind: str) -> bytes:
  data = bytearray(data)
  if kind == "truncate":
    return bytes(data[: int(rng.integers(len(data)))])
  if kind == "flip":
    for _ in range(int(rng.integers(1, 5))):
      data[int(rng.integers(len(data)))] ^= 1 << int(rng.integers(8))
    return bytes(data)
  # header: one size / offset / method field of a central record or a local header
  values = [0, 1, 7, 2**31, 2**32 - 1, int(rng.integers(2**32)), len(data), len(data) + 1]
  records = _central_records(bytes(data))
  at = records[int(rng.integers(len(records)))]
  field, fmt = [(10, "<H"), (20, "<I"), (24, "<I"), (42, "<I"), (28, "<H")][int(rng.integers(5))]
  value = values[int(rng.integers(len(values)))] % (2**16 if fmt == "<H" else 2**32)
  data[at + field : at + field + struct.calcsize(fmt)] = struct.pack(fmt, value)
  return bytes(data)


def _mutate_pickle(rng, pkl: bytes) -> bytes:
  pkl = bytearray(pkl)
  at = int(rng.integers(len(pkl)))
  kind = int(rng.integers(4))
  if kind == 0:
    pkl[at] = OPCODES[int(rng.integers(len(OPCODES)))]
  elif kind == 1:
    pkl[at:at] = bytes([OPCODES[int(rng.integers(len(OPCODES)))]])
  elif kind == 2:
    del pkl[at : at + int(rng.integers(1, 9))]
  else:
    pkl[at] = int(rng.integers(256))
  return bytes(pkl)


def _random_view(rng):
  """(tensor spec, want): a torch-made view (must read) or random numbers (must read as
  the gather says, or be refused where they leave the storage or repeat elements)."""
  numel = int(rng.integers(1, 64))
  base = rng.normal(size=numel).astype(np.float32)
  if rng.random() < 0.4:  # a slice / transpose of a contiguous array: must be read
    shape = tuple(int(n) for n in rng.integers(1, 5, size=int(rng.integers(1, 4))))
    full = np.arange(math.prod(shape)).reshape(shape).transpose(rng.permutation(len(shape)))
    view = full[
        tuple(slice(int(rng.integers(0, n)), None, int(rng.integers(1, 3))) for n in full.shape)
    ]
    base = rng.normal(size=full.size).astype(np.float32)
    offset, stride = int(view.flat[0]), tuple(s // full.itemsize for s in view.strides)
    return (
        fx._Tensor("t", base, offset, view.shape, stride),
        (READ, _gather(base, offset, view.shape, stride)),
    )
  ndim = int(rng.integers(0, 4))
  size = tuple(int(n) for n in rng.integers(0, 6, size=ndim))
  stride = tuple(int(s) for s in rng.integers(-2, 9, size=ndim))
  offset = int(rng.integers(-1, numel + 1))
  spec = fx._Tensor("t", base, offset, size, stride)
  if math.prod(size) == 0:
    return spec, (READ, np.zeros(size, np.float32)) if offset >= 0 else (REFUSE, None)
  flat = _flat(offset, size, stride).ravel()
  if flat.min() < 0 or flat.max() >= numel or np.unique(flat).size < flat.size:
    return spec, (REFUSE, None)
  return spec, (MAYBE, _gather(base, offset, size, stride))  # the reader may refuse some


def _nested(rng):
  depth = int(rng.choice([int(rng.integers(1, 29)), int(rng.integers(36, 80))]))
  obj = np.arange(3, dtype=np.int64)
  for _ in range(depth):
    obj = [{"k": obj}, [obj], (obj, 1)][int(rng.integers(3))]
  return obj, depth


def make_case(rng, clean_bytes, monkeypatch, path):
  """Writes one case to `path`; returns (its kind, what its read must give)."""
  kind = ["truncate", "flip", "header", "pickle", "view", "nested"][int(rng.integers(6))]
  if kind in ("truncate", "flip", "header"):
    path.write_bytes(_mutate_bytes(rng, clean_bytes, kind))
    return kind, (REFUSE, None) if kind == "truncate" else (MAYBE, _expected(_clean()))
  if kind == "pickle":
    pkl, storages = fx.pickled(_clean(), monkeypatch)
    fx.write_archive(path, _mutate_pickle(rng, pkl), storages, NAME)
    return kind, (ANY, None)
  if kind == "view":
    spec, (mode, want) = _random_view(rng)
    fx.write_pt(path, {"w": spec}, monkeypatch, NAME)
    return kind, (mode, {"w": want})
  obj, depth = _nested(rng)
  fx.write_pt(path, {"x": obj}, monkeypatch, NAME)
  return kind, (READ, {"x": obj}) if depth <= 28 else (REFUSE, None)


def _check(path, mode, want) -> tuple[str, int]:
  size = path.stat().st_size
  tracemalloc.reset_peak()
  before = tracemalloc.get_traced_memory()[0]
  try:
    got = torch_zip.read_pt(path)
  except torch_zip.TorchFileError as e:
    text = str(e)
    assert text.startswith(f"{path}: ") and "\n" not in text and len(text) < 700, text
    assert mode != READ, text
    outcome = "error"
  else:
    assert mode != REFUSE, "read, must be refused"
    assert _plain(got) <= 2 * size
    assert mode == ANY or _equal(got, want), (got, want)
    outcome = "read"
  peak = tracemalloc.get_traced_memory()[1] - before
  assert peak < 80 * size + (2 << 20), (peak, size)
  return outcome, peak


def run_fuzz(num_cases: int, seed: int, tmp_path, monkeypatch) -> dict:
  rng = np.random.default_rng(seed)
  clean = tmp_path / "clean.pt"
  fx.write_pt(clean, _clean(), monkeypatch, NAME)
  assert _equal(torch_zip.read_pt(clean), _expected(_clean()))
  clean_bytes = clean.read_bytes()
  counts = collections.Counter()
  tracemalloc.start()
  try:
    for index in range(num_cases):
      path = tmp_path / f"case{index % 8}.pt"
      kind, (mode, want) = make_case(rng, clean_bytes, monkeypatch, path)
      outcome, peak = _check(path, mode, want)
      counts[f"{kind} {outcome}"] += 1
      counts["max peak bytes"] = max(counts["max peak bytes"], peak)
  finally:
    tracemalloc.stop()
  return counts


def _assert_both(counts, at_least):
  for kind in ("flip", "header", "pickle", "view", "nested"):
    for outcome in ("read", "error"):
      assert counts[f"{kind} {outcome}"] >= at_least, counts
  assert counts["truncate error"] >= at_least, counts


def test_fuzz_torch_zip_reader(tmp_path, monkeypatch):
  counts = run_fuzz(200, seed=0, tmp_path=tmp_path, monkeypatch=monkeypatch)
  print(dict(counts))
  _assert_both(counts, 1)


@pytest.mark.slow
def test_fuzz_torch_zip_reader_many(tmp_path, monkeypatch):
  counts = run_fuzz(5000, seed=1, tmp_path=tmp_path, monkeypatch=monkeypatch)
  print(dict(counts))
  _assert_both(counts, 20)
