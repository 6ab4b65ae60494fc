"""The tensors of a `.pt` file (`torch_zip.read_pt`) built from their storages, and the
whole result checked: only plain containers of numbers, strings, bytes, None and tensors,
nested at most `MAX_DEPTH` deep, without cycles, at most `MAX_OBJECTS` of them; each view
checked before it is built (integer offset, sizes and strides, no broadcast, reversed or
overlapping dimensions, within its storage, all tensors within twice the file's length),
then copied into a native-order numpy array.
"""

import collections
import math
import zipfile

import numpy as np

MAX_DEPTH = 32  # container nesting of the result
MAX_OBJECTS = 1 << 16  # containers and tensors in the result
MAX_DIM = 1 << 40  # elements along one dimension


class Refused(Exception):
  """A problem inside a read; `read_pt` prefixes the file's name."""


def _bfloat16(raw: np.ndarray) -> np.ndarray:
  return (raw.astype(np.uint32) << 16).view(np.float32)


# torch storage type -> (numpy dtype of the raw buffer, conversion or None)
STORAGES = {
    "FloatStorage": (np.float32, None),
    "DoubleStorage": (np.float64, None),
    "HalfStorage": (np.float16, None),
    "BFloat16Storage": (np.uint16, _bfloat16),
    "LongStorage": (np.int64, None),
    "IntStorage": (np.int32, None),
    "ShortStorage": (np.int16, None),
    "CharStorage": (np.int8, None),
    "ByteStorage": (np.uint8, None),
    "BoolStorage": (np.uint8, lambda raw: raw != 0),
}
SCALARS = (str, bytes, int, float, type(None))  # bool is an int


class StorageType:
  """Stands for a torch storage class (`torch.<name>`) in a persistent id."""

  def __init__(self, name: str):
    self.name = name


class StorageRef:
  """A storage entry of the archive, checked but not yet read."""

  def __init__(self, info: zipfile.ZipInfo, kind: str, numel: int):
    self.info, self.kind, self.numel = info, kind, numel


class TensorArgs:
  """The arguments of one `_rebuild_tensor_v2`, materialised by `TensorBuilder.resolve`."""

  def __init__(self, storage, offset, size, stride):
    self.storage, self.offset, self.size, self.stride = storage, offset, size, stride


def describe(obj) -> str:
  """What `obj` is, for a message."""
  if isinstance(obj, StorageType):
    return f"torch.{obj.name}"
  return {StorageRef: "a storage", TensorArgs: "a tensor"}.get(type(obj), type(obj).__name__)


def is_int(x) -> bool:
  return type(x) is int


class TensorBuilder:
  """Builds the arrays of one read: `resolve` the unpickled tree."""

  def __init__(self, read_entry, byteorder: str, length: int):
    self._read_entry, self._length = read_entry, length  # read_entry(info) -> bytes
    self._order = "<" if byteorder == "little" else ">"
    self._budget = 2 * length  # bytes the tensors may add up to
    self._arrays, self._done, self._open = {}, {}, set()

  def resolve(self, obj, path: tuple = (), depth: int = 0):
    """`obj` with each `TensorArgs` materialised as an array, checked as the module says."""
    if isinstance(obj, SCALARS):
      return obj
    if id(obj) in self._done:
      return self._done[id(obj)]
    where = lambda: ".".join(map(str, path)) or "the top-level object"
    if id(obj) in self._open or depth >= MAX_DEPTH:
      raise Refused(f"{where()}: containers nested deeper than {MAX_DEPTH} or in a cycle")
    if len(self._done) >= MAX_OBJECTS:
      raise Refused(f"{where()}: more than {MAX_OBJECTS} containers and tensors")
    kind = type(obj)
    self._open.add(id(obj))
    if kind is TensorArgs:
      out = self._materialise(obj, where())
    elif kind in (dict, collections.OrderedDict):
      out = kind((k, self.resolve(v, path + (k,), depth + 1)) for k, v in obj.items())
    elif kind in (list, tuple):
      out = kind(self.resolve(v, path + (i,), depth + 1) for i, v in enumerate(obj))
    else:
      raise Refused(
          f"{where()}: holds {describe(obj)}, not a container, number, string or " "tensor"
      )
    self._open.discard(id(obj))
    self._done[id(obj)] = out
    return out

  def _materialise(self, t: TensorArgs, where: str) -> np.ndarray:
    ref, offset, size, stride = t.storage, t.offset, t.size, t.stride
    what = f"tensor {where} (storage {ref.info.filename})"
    if not (
        is_int(offset)
        and type(size) is tuple
        and type(stride) is tuple
        and all(map(is_int, size + stride))
        and len(size) == len(stride) <= 32
    ):
      raise Refused(
          f"{what}: offset, size and stride must be an integer and two equally "
          f"long tuples of integers, got {describe(offset)}, {describe(size)}, "
          f"{describe(stride)}"
      )
    if offset < 0 or any(n < 0 or n > MAX_DIM for n in size):
      raise Refused(f"{what}: offset {offset} or size {size} out of range")
    dtype, convert = STORAGES[ref.kind]
    out_dtype = np.dtype(np.float32 if convert is _bfloat16 else dtype)
    numel = math.prod(size)
    if numel == 0:
      return np.zeros(size, bool if ref.kind == "BoolStorage" else out_dtype)
    extent = 1  # elements spanned by the dimensions of smaller stride
    for n, s in sorted((p for p in zip(size, stride) if p[0] > 1), key=lambda p: p[1]):
      if s < extent:
        raise Refused(
            f"{what}: size {size} with stride {stride} is a broadcast, reversed "
            "or overlapping view; only views of distinct elements are read"
        )
      extent += (n - 1) * s
    if offset + extent > ref.numel:
      raise Refused(
          f"{what}: size {size}, stride {stride}, offset {offset} exceeds its "
          f"storage of {ref.numel} elements"
      )
    self._budget -= numel * out_dtype.itemsize
    if self._budget < 0:
      raise Refused(
          f"{what}: the tensors add up to more than twice the file's "
          f"{self._length} bytes (views sharing their storage)"
      )
    key = ref.info.filename
    if key not in self._arrays:
      raw = self._read_entry(ref.info)
      self._arrays[key] = np.frombuffer(
          raw, np.dtype(dtype).newbyteorder(self._order), count=ref.numel
      )
    data = self._arrays[key]
    view = np.lib.stride_tricks.as_strided(
        data[offset:], shape=size, strides=[s * data.itemsize for s in stride], writeable=False
    )
    array = np.array(view, dtype=np.dtype(dtype))  # native byte order, contiguous
    return convert(array) if convert else array
