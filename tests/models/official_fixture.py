"""Test fixtures written from the official cVMDx U-Net's structure (not its code): a
random state dict with the official parameter names and PyTorch shapes, a float64
numpy forward pass of that model in the official (channels-first) conventions, and a
torch-free writer of `torch.save` zip files."""

import io
import math
import pickle
import struct
import sys
import types
import zipfile
import zlib

import numpy as np

GROUPS = 32  # the official GroupNorm32
EPS = 1e-5
PADDED = 128


def state_dict(rng, q, ch=32, mult=(1, 2), nrb=1, attn_levels=(1,), emb_mult=2):
  """{official name: float32 array} for UNetModel(in=2, model_channels=ch, out=2,
  channel_mult=mult, num_res_blocks=nrb, attention at attn_levels, num_classes=q + 1,
  use_scale_shift_norm=True); every tensor random (no zero-initialised layers)."""
  emb = emb_mult * ch
  sd = {}

  def lin(name, i, o):
    sd[f"{name}.weight"] = rng.normal(0, 1 / math.sqrt(i), (o, i))
    sd[f"{name}.bias"] = rng.normal(0, 0.1, o)

  def conv(name, i, o, k=3):
    sd[f"{name}.weight"] = rng.normal(0, 1 / math.sqrt(i * k), (o, i, k))
    sd[f"{name}.bias"] = rng.normal(0, 0.1, o)

  def norm(name, c):
    sd[f"{name}.weight"] = 1 + rng.normal(0, 0.2, c)
    sd[f"{name}.bias"] = rng.normal(0, 0.2, c)

  def res(name, i, o):
    norm(f"{name}.in_layers.0", i)
    conv(f"{name}.in_layers.2", i, o)
    lin(f"{name}.emb_layers.1", emb, 2 * o)
    norm(f"{name}.out_layers.0", o)
    conv(f"{name}.out_layers.3", o, o)
    if i != o:
      conv(f"{name}.skip_connection", i, o, 1)

  def attn(name, c):
    norm(f"{name}.norm", c)
    conv(f"{name}.qkv", c, 3 * c, 1)
    conv(f"{name}.proj_out", c, c, 1)

  lin("time_embed.0", ch, emb)
  lin("time_embed.2", emb, emb)
  sd["label_emb.weight"] = rng.normal(0, 0.5, (q + 1, emb))
  conv("input_blocks.0.0", 2, ch)
  skips, cur, i = [ch], ch, 1
  for level, m in enumerate(mult):
    for _ in range(nrb):
      res(f"input_blocks.{i}.0", cur, m * ch)
      cur = m * ch
      if level in attn_levels:
        attn(f"input_blocks.{i}.1", cur)
      skips.append(cur)
      i += 1
    if level < len(mult) - 1:
      conv(f"input_blocks.{i}.0.op", cur, cur)
      skips.append(cur)
      i += 1
  res("middle_block.0", cur, cur)
  attn("middle_block.1", cur)
  res("middle_block.2", cur, cur)
  o = 0
  for level, m in reversed(list(enumerate(mult))):
    for j in range(nrb + 1):
      res(f"output_blocks.{o}.0", cur + skips.pop(), m * ch)
      cur, k = m * ch, 1
      if level in attn_levels:
        attn(f"output_blocks.{o}.1", cur)
        k = 2
      if level and j == nrb:
        conv(f"output_blocks.{o}.{k}.conv", cur, cur)
      o += 1
  norm("out.0", cur)
  conv("out.2", cur, 2)
  return {k: v.astype(np.float32) for k, v in sd.items()}


def _silu(x):
  return x / (1 + np.exp(-x))


def forward(sd, x, t, y, *, mult=(1, 2), nrb=1, attn_levels=(1,), heads=4, left=None):
  """The official U-Net on x (B, 2, 125) channels-first, float64 -> (B, 2, 125);
  `left`: zeros padded on the left (official: centred, (128 - 125) // 2 = 1)."""
  p = {k: v.astype(np.float64) for k, v in sd.items()}

  def gn(h, name):
    b, c, n = h.shape
    g = h.reshape(b, GROUPS, -1)
    g = (g - g.mean(-1, keepdims=True)) / np.sqrt(g.var(-1, keepdims=True) + EPS)
    return g.reshape(b, c, n) * p[f"{name}.weight"][:, None] + p[f"{name}.bias"][:, None]

  def conv(h, name, stride=1):
    w = p[f"{name}.weight"]
    k = w.shape[2]
    hp = np.pad(h, ((0, 0), (0, 0), ((k - 1) // 2, (k - 1) // 2)))
    n_out = (hp.shape[2] - k) // stride + 1
    taps = np.stack([hp[:, :, j : j + stride * (n_out - 1) + 1 : stride] for j in range(k)], -1)
    return np.einsum("binj,oij->bon", taps, w) + p[f"{name}.bias"][:, None]

  def lin(h, name):
    return h @ p[f"{name}.weight"].T + p[f"{name}.bias"]

  def res(h, name):
    a = conv(_silu(gn(h, f"{name}.in_layers.0")), f"{name}.in_layers.2")
    scale, shift = np.split(lin(_silu(emb), f"{name}.emb_layers.1"), 2, axis=1)
    a = gn(a, f"{name}.out_layers.0") * (1 + scale[:, :, None]) + shift[:, :, None]
    a = conv(_silu(a), f"{name}.out_layers.3")
    skip = conv(h, f"{name}.skip_connection") if f"{name}.skip_connection.weight" in p else h
    return skip + a

  def attn(h, name):
    b, c, n = h.shape
    qkv = conv(gn(h, f"{name}.norm"), f"{name}.qkv").reshape(b * heads, 3 * c // heads, n)
    q, k, v = np.split(qkv, 3, axis=1)  # per head: [q_h, k_h, v_h]
    s = 1 / math.sqrt(math.sqrt(c // heads))
    w = np.einsum("bct,bcs->bts", q * s, k * s)
    w = np.exp(w - w.max(-1, keepdims=True))
    w /= w.sum(-1, keepdims=True)
    out = np.einsum("bts,bcs->bct", w, v).reshape(b, c, n)
    return h + conv(out, f"{name}.proj_out")

  ch = p["input_blocks.0.0.weight"].shape[0]
  half = ch // 2
  args = np.asarray(t, np.float64)[:, None] * np.exp(-math.log(10000) * np.arange(half) / half)
  temb = np.concatenate([np.cos(args), np.sin(args)], axis=1)
  emb = lin(_silu(lin(temb, "time_embed.0")), "time_embed.2") + p["label_emb.weight"][y]
  length = x.shape[2]
  left = (PADDED - length) // 2 if left is None else left  # official: 1 left, 2 right
  h = conv(
      np.pad(x.astype(np.float64), ((0, 0), (0, 0), (left, PADDED - length - left))),
      "input_blocks.0.0",
  )
  hs, i = [h], 1
  for level in range(len(mult)):
    for _ in range(nrb):
      h = res(h, f"input_blocks.{i}.0")
      if level in attn_levels:
        h = attn(h, f"input_blocks.{i}.1")
      hs.append(h)
      i += 1
    if level < len(mult) - 1:
      h = conv(h, f"input_blocks.{i}.0.op", stride=2)  # padding 1: output j sees 2j-1..2j+1
      hs.append(h)
      i += 1
  h = res(attn(res(h, "middle_block.0"), "middle_block.1"), "middle_block.2")
  o = 0
  for level in reversed(range(len(mult))):
    for j in range(nrb + 1):
      h = res(np.concatenate([h, hs.pop()], axis=1), f"output_blocks.{o}.0")
      k = 1
      if level in attn_levels:
        h = attn(h, f"output_blocks.{o}.1")
        k = 2
      if level and j == nrb:
        h = conv(np.repeat(h, 2, axis=2), f"output_blocks.{o}.{k}.conv")
      o += 1
  out = conv(_silu(gn(h, "out.0")), "out.2")
  return out[:, :, left : left + length]


_STORAGE = {np.dtype(np.float32): "FloatStorage", np.dtype(np.int64): "LongStorage"}


class _Tensor:
  """Pickles as torch._utils._rebuild_tensor_v2(storage, offset, size, stride, ...)."""

  def __init__(self, key, array, offset=0, size=None, stride=None):
    self.key, self.array = key, array
    self.offset = offset
    self.size = array.shape if size is None else size
    self.stride = tuple(s // array.itemsize for s in array.strides) if stride is None else stride

  def __reduce__(self):
    import torch._utils  # the stand-in module installed by `write_pt`

    return (
        torch._utils._rebuild_tensor_v2,
        (
            _StorageRef(self.key, self.array),
            self.offset,
            tuple(self.size),
            tuple(self.stride),
            False,
            {},
        ),
    )


class _StorageRef:

  def __init__(self, key, array):
    self.key, self.array = key, array


def pickled(obj, monkeypatch) -> tuple[bytes, dict]:
  """`obj` (dicts, lists, tuples, numbers, `_Tensor`s, numpy arrays) pickled as
  torch.save does (protocol 2, storages as persistent ids): (pickle, {key: array})."""
  torch_mod = types.ModuleType("torch")
  utils_mod = types.ModuleType("torch._utils")

  def _rebuild_tensor_v2(*args):
    raise AssertionError("never called while writing")

  _rebuild_tensor_v2.__module__ = "torch._utils"
  _rebuild_tensor_v2.__qualname__ = "_rebuild_tensor_v2"
  utils_mod._rebuild_tensor_v2 = _rebuild_tensor_v2
  torch_mod._utils = utils_mod
  for storage in _STORAGE.values():
    cls = type(storage, (), {"__module__": "torch"})
    setattr(torch_mod, storage, cls)
  monkeypatch.setitem(sys.modules, "torch", torch_mod)
  monkeypatch.setitem(sys.modules, "torch._utils", utils_mod)

  storages = {}
  counter = iter(range(10**6))

  def wrap(value):
    if isinstance(value, np.ndarray):
      return _Tensor(str(next(counter)), np.array(value, order="C"))  # 0-d stays 0-d
    if isinstance(value, dict):
      out = type(value)((k, wrap(v)) for k, v in value.items())
      if hasattr(value, "__dict__"):  # e.g. a state dict's _metadata
        vars(out).update(vars(value))
      return out
    if type(value) in (list, tuple):
      return type(value)(map(wrap, value))
    return value

  class Pickler(pickle.Pickler):

    def persistent_id(self, o):
      if isinstance(o, _StorageRef):
        storages[o.key] = o.array
        return ("storage", getattr(torch_mod, _STORAGE[o.array.dtype]), o.key, "cpu", o.array.size)
      return None

  buf = io.BytesIO()
  Pickler(buf, protocol=2).dump(wrap(obj))
  return buf.getvalue(), storages


def write_archive(path, pkl: bytes, storages: dict, name="archive"):
  """A torch.save zip file: `<name>/data.pkl` + `<name>/data/<key>` (stored)."""
  with zipfile.ZipFile(path, "w") as z:
    z.writestr(f"{name}/data.pkl", pkl)
    z.writestr(f"{name}/byteorder", "little")
    for key, array in storages.items():
      z.writestr(f"{name}/data/{key}", array.astype(array.dtype.newbyteorder("<")).tobytes())
    z.writestr(f"{name}/version", "3\n")


def write_pt(path, obj, monkeypatch, name="archive"):
  """Writes `obj` (as `pickled` takes it) as a torch.save zip file."""
  write_archive(path, *pickled(obj, monkeypatch), name=name)


def _local_header(name: str, payload: bytes, method: int, size: int, crc: int) -> bytes:
  return (
      struct.pack(
          "<IHHHHHIIIHH", 0x04034B50, 20, 0, method, 0, 0, crc, len(payload), size, len(name), 0
      )
      + name.encode()
  )


def write_zip(path, blob: bytes, records: list[tuple]):
  """A zip file of `blob` (local headers and payloads) and a central directory of
  `records` (name, method, local header offset, stored length, size, crc)."""
  central = b"".join(
      struct.pack(
          "<IHHHHHHIIIHHHHHII",
          0x02014B50,
          20,
          20,
          0,
          method,
          0,
          0,
          crc,
          stored,
          size,
          len(name),
          0,
          0,
          0,
          0,
          0,
          offset,
      )
      + name.encode()
      for name, method, offset, stored, size, crc in records
  )
  end = struct.pack(
      "<IHHHHIIH", 0x06054B50, 0, 0, len(records), len(records), len(central), len(blob), 0
  )
  path.write_bytes(blob + central + end)


def write_entries(path, entries: list[tuple]):
  """A zip file of (name, payload, method, size, crc) entries, one after the other."""
  blob, records = b"", []
  for name, payload, method, size, crc in entries:
    records.append((name, method, len(blob), len(payload), size, crc))
    blob += _local_header(name, payload, method, size, crc) + payload
  write_zip(path, blob, records)


def write_deflate_bomb(path, pkl: bytes, name: str, size: int):
  """A zip file of `<name>/data.pkl` (`pkl`, stored) and a deflated `<name>/data/0` of
  `size` zero bytes (size a multiple of 1 MiB), the archive ~size / 1000 bytes."""
  chunk = 1 << 20
  block = zlib.compressobj(9, zlib.DEFLATED, -15)
  block = block.compress(bytes(chunk)) + block.flush(zlib.Z_FULL_FLUSH)  # no back-reference
  crc = 0
  for _ in range(size // chunk):
    crc = zlib.crc32(bytes(chunk), crc)
  write_entries(
      path,
      [
          (f"{name}/data.pkl", pkl, zipfile.ZIP_STORED, len(pkl), zlib.crc32(pkl)),
          (
              f"{name}/data/0",
              block * (size // chunk) + b"\x03\x00",  # final block
              zipfile.ZIP_DEFLATED,
              size,
              crc,
          ),
      ],
  )


def write_nested_entries(path, pkl: bytes, name: str, payload: bytes, depth: int):
  """A zip file of `<name>/data.pkl` and storages `<name>/data/0..depth-1`, each stored
  entry's payload holding the next entry (header and payload): entries sharing bytes."""
  inner = b""
  for key in reversed(range(depth)):
    inner = (
        _local_header(
            f"{name}/data/{key}",
            inner + payload,
            zipfile.ZIP_STORED,
            len(inner + payload),
            zlib.crc32(inner + payload),
        )
        + inner
        + payload
    )
  head = _local_header(f"{name}/data.pkl", pkl, zipfile.ZIP_STORED, len(pkl), zlib.crc32(pkl))
  records = [(f"{name}/data.pkl", 0, 0, len(pkl), len(pkl), zlib.crc32(pkl))]
  offset, rest = len(head + pkl), inner
  for key in range(depth):
    header = 30 + len(f"{name}/data/{key}")
    body = rest[header:]
    records.append((f"{name}/data/{key}", 0, offset, len(body), len(body), zlib.crc32(body)))
    offset, rest = offset + header, body[: len(body) - len(payload)]
  write_zip(path, head + pkl + inner, records)
