"""Reads PyTorch `.pt` files (the zip format of `torch.save`, PyTorch >= 1.6) without
torch, as numpy arrays, in memory bounded by the file's length.

A `.pt` file is a zip archive `<name>/data.pkl` (a pickle) plus one raw little- or
big-endian buffer per tensor storage, `<name>/data/<key>` (`<name>/byteorder` says
which; absent means little). The pickle rebuilds each tensor with
`torch._utils._rebuild_tensor_v2(storage, offset, size, stride, ...)`, the storage
named by a persistent id `("storage", torch.<Type>Storage, key, location, numel)`.

What is refused (`TorchFileError`, one line naming the file and the entry, storage or
tensor; nothing of the file is executed, and each read starts from fresh objects):
- zip entries, by their central-directory header before they are read: a compressed
  entry (torch stores every entry uncompressed), a pickle over `MAX_PICKLE_BYTES`, a
  storage entry smaller than its declared `numel` elements, entries that together
  exceed the archive's length (entries sharing bytes);
- the pickle: any opcode outside `_OPCODES` (no INST / OBJ / NEWOBJ / EXT, no sets),
  any global outside `_GLOBALS`; REDUCE calls only the tensor and parameter rebuilds
  and `OrderedDict()`; SETITEM(S) only on a dict or OrderedDict with number or string
  keys, APPEND(S) only on a list, BUILD only on an OrderedDict (torch's `_metadata` of
  a state dict, which is dropped);
- the result: anything but dicts, lists and tuples of numbers, strings, bytes, None
  and tensors; containers nested deeper than `MAX_DEPTH`, or cyclic; more than
  `MAX_OBJECTS` containers and tensors;
- tensors, before any view is built: offset, sizes and strides that are not
  integers; a stride <= 0 on a dimension of size > 1 (a broadcast or reversed view);
  overlapping dimensions (ordered by stride, each must step past the extent of the
  smaller ones, as every slice, transpose and narrowing of torch does); a view past
  the end of its storage; tensors together larger than twice the file.

Memory ceiling: a read of a file of L bytes allocates the pickle (<= `MAX_PICKLE_BYTES`)
and the Python objects it builds (measured: at most ~75 bytes per pickle byte, a stack
of empty dicts, so < 40 MB), the storage entries it uses (<= L bytes), the tensors
(<= 2 L) and one tensor's conversion (<= 2 L): peak <= 5 L + 40 MB.
"""

import collections
import io
import math
import pickle
import zipfile
from pathlib import Path

import numpy as np

MAX_PICKLE_BYTES = 1 << 19  # ~4,500 tensors; the official U-Net's (227 tensors) is 26 kB
MAX_DEPTH = 32  # container nesting of the result
MAX_OBJECTS = 1 << 16  # containers and tensors in the result
MAX_DIM = 1 << 40  # elements along one dimension


class TorchFileError(ValueError):
  """A file that is not a readable plain-tensor `.pt` archive."""


class _Refused(Exception):
  """A problem inside a read; `read_pt` prefixes the file's name."""


def _bfloat16(raw: np.ndarray) -> np.ndarray:
  return (raw.astype(np.uint32) << 16).view(np.float32)


# torch storage type -> (numpy dtype of the raw buffer, conversion or None)
_STORAGES = {
    "FloatStorage": (np.float32, None), "DoubleStorage": (np.float64, None),
    "HalfStorage": (np.float16, None), "BFloat16Storage": (np.uint16, _bfloat16),
    "LongStorage": (np.int64, None), "IntStorage": (np.int32, None),
    "ShortStorage": (np.int16, None), "CharStorage": (np.int8, None),
    "ByteStorage": (np.uint8, None), "BoolStorage": (np.uint8, lambda raw: raw != 0),
}
_OPCODES = (
    "PROTO FRAME STOP MARK POP POP_MARK DUP NONE NEWTRUE NEWFALSE INT BININT BININT1 BININT2 "
    "LONG LONG1 LONG4 FLOAT BINFLOAT STRING BINSTRING SHORT_BINSTRING UNICODE BINUNICODE "
    "SHORT_BINUNICODE BINUNICODE8 BINBYTES SHORT_BINBYTES BINBYTES8 EMPTY_TUPLE TUPLE TUPLE1 "
    "TUPLE2 TUPLE3 EMPTY_LIST LIST APPEND APPENDS EMPTY_DICT SETITEM SETITEMS GET BINGET "
    "LONG_BINGET PUT BINPUT LONG_BINPUT MEMOIZE GLOBAL STACK_GLOBAL REDUCE BUILD BINPERSID"
).split()
_SCALARS = (str, bytes, int, float, type(None))  # bool is an int


class _StorageType:
  """Stands for a torch storage class (`torch.<name>`) in a persistent id."""

  def __init__(self, name: str):
    self.name = name


class _StorageRef:
  """A storage entry of the archive, checked but not yet read."""

  def __init__(self, info: zipfile.ZipInfo, kind: str, numel: int):
    self.info, self.kind, self.numel = info, kind, numel


class _Tensor:
  """The arguments of one `_rebuild_tensor_v2`, materialised by `_Reader.resolve`."""

  def __init__(self, storage, offset, size, stride):
    self.storage, self.offset, self.size, self.stride = storage, offset, size, stride


def _kind(obj) -> str:
  if isinstance(obj, _StorageType):
    return f"torch.{obj.name}"
  return {_StorageRef: "a storage", _Tensor: "a tensor"}.get(type(obj), type(obj).__name__)


def _is_int(x) -> bool:
  return type(x) is int


def _entry(archive: zipfile.ZipFile, name: str, limit: int) -> zipfile.ZipInfo:
  """The header of entry `name`, checked: stored uncompressed, at most `limit` bytes."""
  try:
    info = archive.getinfo(name)
  except KeyError:
    raise _Refused(f"entry {name} missing from the archive") from None
  if info.compress_type != zipfile.ZIP_STORED:
    raise _Refused(f"entry {name} is compressed (method {info.compress_type}); torch.save "
                   "stores entries uncompressed")
  if info.file_size != info.compress_size:
    raise _Refused(f"entry {name} declares {info.file_size} bytes but stores "
                   f"{info.compress_size}")
  if info.file_size > limit:
    raise _Refused(f"entry {name} declares {info.file_size} bytes, more than the {limit} "
                   "allowed")
  return info


class _Dispatch(dict):
  """The opcode table: a missing opcode is refused (nothing is inserted)."""

  def __missing__(self, opcode: int):
    raise _Refused(f"the pickle uses opcode {bytes([opcode])!r}, outside those of plain "
                   "containers and tensors (object construction, extensions, sets, buffers)")


class _Reader(pickle._Unpickler):  # the Python VM, so that opcodes can be restricted
  """One read of one archive: the restricted unpickler plus the tensor builder."""

  def __init__(self, archive: zipfile.ZipFile, prefix: str, byteorder: str, length: int):
    self._archive, self._prefix, self._length = archive, prefix, length
    self._order = "<" if byteorder == "little" else ">"
    self._unread = length  # bytes the entries still read may add up to
    self._budget = 2 * length  # bytes the tensors may add up to
    self._types = {name: _StorageType(name) for name in _STORAGES}
    self._rebuilds = (self._rebuild_tensor, self._rebuild_parameter, collections.OrderedDict)
    self._globals = {
        ("collections", "OrderedDict"): collections.OrderedDict,
        ("torch._utils", "_rebuild_tensor_v2"): self._rebuilds[0],
        ("torch._utils", "_rebuild_parameter"): self._rebuilds[1],
        ("torch._utils", "_rebuild_parameter_with_state"): self._rebuilds[1],
        **{("torch", name): t for name, t in self._types.items()}}
    self._refs, self._arrays, self._done, self._open = {}, {}, {}, set()
    pkl = _entry(archive, f"{prefix}data.pkl", MAX_PICKLE_BYTES)
    super().__init__(io.BytesIO(self._read(pkl)))

  def _read(self, info: zipfile.ZipInfo) -> bytes:
    self._unread -= info.file_size
    if self._unread < 0:
      raise _Refused(f"entry {info.filename}: the entries read add up to more than the "
                     f"archive's {self._length} bytes")
    return self._archive.read(info)

  # ------------------------------------------------------------- the pickle VM

  def find_class(self, module, name):
    try:
      return self._globals[(module, name)]
    except KeyError:
      raise _Refused(f"the pickle names {module}.{name}, which is not a tensor, parameter or "
                     "plain container; only state dicts of tensors (possibly inside dicts) "
                     "are read") from None

  def persistent_load(self, pid):
    if not (type(pid) is tuple and len(pid) == 5 and pid[0] == "storage"
            and any(pid[1] is t for t in self._types.values()) and type(pid[2]) is str
            and _is_int(pid[4]) and pid[4] >= 0):
      raise _Refused(f"unsupported persistent id (a {_kind(pid)}); expected ('storage', "
                     "torch.<Type>Storage, key, location, numel)")
    _, storage_type, key, _, numel = pid
    ref = self._refs.get(key)
    if ref is None:
      info = _entry(self._archive, f"{self._prefix}data/{key}", self._length)
      itemsize = np.dtype(_STORAGES[storage_type.name][0]).itemsize
      if numel * itemsize > info.file_size:
        raise _Refused(f"storage {info.filename} declares {numel} elements of "
                       f"{storage_type.name} ({numel * itemsize} bytes), the entry holds "
                       f"{info.file_size}")
      ref = self._refs[key] = _StorageRef(info, storage_type.name, numel)
    if (ref.kind, ref.numel) != (storage_type.name, numel):
      raise _Refused(f"storage {ref.info.filename} is named as {ref.kind} of {ref.numel} "
                     f"elements and as {storage_type.name} of {numel}")
    return ref

  def _rebuild_tensor(self, storage, offset, size, stride, *unused):
    del unused  # requires_grad, backward hooks, metadata
    if type(storage) is not _StorageRef:
      raise _Refused(f"a tensor rebuilt from {_kind(storage)}, not a storage")
    return _Tensor(storage, offset, size, stride)

  def _rebuild_parameter(self, data, *unused):
    del unused
    if type(data) is not _Tensor:
      raise _Refused(f"a parameter rebuilt from {_kind(data)}, not a tensor")
    return data

  def _load_reduce(self):
    args = self.stack.pop()
    func = self.stack[-1]
    if not any(func is f for f in self._rebuilds) or type(args) is not tuple:
      raise _Refused(f"REDUCE calls {_kind(func)}; only tensor and parameter rebuilds are "
                     "called")
    if func is collections.OrderedDict and args:
      raise _Refused("REDUCE calls OrderedDict with arguments")
    self.stack[-1] = func(*args)

  def _set_items(self, items):
    target = self.stack[-1]
    if type(target) not in (dict, collections.OrderedDict):
      raise _Refused(f"SETITEM on {_kind(target)}, not a dict")
    if len(items) % 2:
      raise _Refused("SETITEMS with a key but no value")
    for key, value in zip(items[::2], items[1::2]):
      if not isinstance(key, _SCALARS):
        raise _Refused(f"a dict key of type {_kind(key)}; keys are numbers or strings")
      target[key] = value

  def _append_items(self, items):
    target = self.stack[-1]
    if type(target) is not list:
      raise _Refused(f"APPEND on {_kind(target)}, not a list")
    target.extend(items)

  def _load_build(self):
    state = self.stack.pop()
    target = self.stack[-1]
    if type(target) is not collections.OrderedDict or type(state) is not dict:
      raise _Refused(f"BUILD sets the state of {_kind(target)}; only an OrderedDict's "
                     "attributes are read (and dropped)")

  dispatch = _Dispatch({op: pickle._Unpickler.dispatch[op]
                        for op in (getattr(pickle, name)[0] for name in _OPCODES)})
  dispatch.update({
      pickle.REDUCE[0]: _load_reduce, pickle.BUILD[0]: _load_build,
      pickle.SETITEM[0]: lambda self: self._set_items([self.stack.pop(-2), self.stack.pop()]),
      pickle.SETITEMS[0]: lambda self: self._set_items(self.pop_mark()),
      pickle.APPEND[0]: lambda self: self._append_items([self.stack.pop()]),
      pickle.APPENDS[0]: lambda self: self._append_items(self.pop_mark())})

  # ------------------------------------------------------------- the result

  def resolve(self, obj, path: tuple = (), depth: int = 0):
    """`obj` with each `_Tensor` materialised as an array, checked as the module says."""
    if isinstance(obj, _SCALARS):
      return obj
    if id(obj) in self._done:
      return self._done[id(obj)]
    where = lambda: ".".join(map(str, path)) or "the top-level object"
    if id(obj) in self._open or depth >= MAX_DEPTH:
      raise _Refused(f"{where()}: containers nested deeper than {MAX_DEPTH} or in a cycle")
    if len(self._done) >= MAX_OBJECTS:
      raise _Refused(f"{where()}: more than {MAX_OBJECTS} containers and tensors")
    kind = type(obj)
    self._open.add(id(obj))
    if kind is _Tensor:
      out = self._materialise(obj, where())
    elif kind in (dict, collections.OrderedDict):
      out = kind((k, self.resolve(v, path + (k,), depth + 1)) for k, v in obj.items())
    elif kind in (list, tuple):
      out = kind(self.resolve(v, path + (i,), depth + 1) for i, v in enumerate(obj))
    else:
      raise _Refused(f"{where()}: holds {_kind(obj)}, not a container, number, string or "
                     "tensor")
    self._open.discard(id(obj))
    self._done[id(obj)] = out
    return out

  def _materialise(self, t: _Tensor, where: str) -> np.ndarray:
    ref, offset, size, stride = t.storage, t.offset, t.size, t.stride
    what = f"tensor {where} (storage {ref.info.filename})"
    if not (_is_int(offset) and type(size) is tuple and type(stride) is tuple
            and all(map(_is_int, size + stride)) and len(size) == len(stride) <= 32):
      raise _Refused(f"{what}: offset, size and stride must be an integer and two equally "
                     f"long tuples of integers, got {_kind(offset)}, {_kind(size)}, "
                     f"{_kind(stride)}")
    if offset < 0 or any(n < 0 or n > MAX_DIM for n in size):
      raise _Refused(f"{what}: offset {offset} or size {size} out of range")
    dtype, convert = _STORAGES[ref.kind]
    out_dtype = np.dtype(np.float32 if convert is _bfloat16 else dtype)
    numel = math.prod(size)
    if numel == 0:
      return np.zeros(size, bool if ref.kind == "BoolStorage" else out_dtype)
    extent = 1  # elements spanned by the dimensions of smaller stride
    for n, s in sorted((p for p in zip(size, stride) if p[0] > 1), key=lambda p: p[1]):
      if s < extent:
        raise _Refused(f"{what}: size {size} with stride {stride} is a broadcast, reversed "
                       "or overlapping view; only views of distinct elements are read")
      extent += (n - 1) * s
    if offset + extent > ref.numel:
      raise _Refused(f"{what}: size {size}, stride {stride}, offset {offset} exceeds its "
                     f"storage of {ref.numel} elements")
    self._budget -= numel * out_dtype.itemsize
    if self._budget < 0:
      raise _Refused(f"{what}: the tensors add up to more than twice the file's "
                     f"{self._length} bytes (views sharing their storage)")
    key = ref.info.filename
    if key not in self._arrays:
      raw = self._read(ref.info)
      self._arrays[key] = np.frombuffer(raw, np.dtype(dtype).newbyteorder(self._order),
                                        count=ref.numel)
    data = self._arrays[key]
    view = np.lib.stride_tricks.as_strided(
        data[offset:], shape=size, strides=[s * data.itemsize for s in stride], writeable=False)
    array = np.array(view, dtype=np.dtype(dtype))  # native byte order, contiguous
    return convert(array) if convert else array


def read_pt(path: str | Path):
  """The object a `torch.save` zip file holds, tensors as numpy arrays.

  Raises:
    TorchFileError: not a zip `.pt` file (e.g. the legacy pre-1.6 format), or one the
      module docstring refuses; the message names the file.
  """
  path = Path(path)
  try:
    archive = zipfile.ZipFile(path)
  except Exception as e:  # zipfile raises many kinds on a damaged directory
    raise TorchFileError(f"{path}: not a PyTorch zip checkpoint ({type(e).__name__}: "
                         f"{str(e)[:200]}); files of torch.save(..., "
                         "_use_new_zipfile_serialization=False) are not read") from None
  with archive:
    try:
      pickles = [n for n in archive.namelist() if n.endswith("/data.pkl") and n.count("/") == 1]
      if len(pickles) != 1:
        raise _Refused(f"expected one <name>/data.pkl in the archive, found {pickles[:4]}")
      prefix = pickles[0][:-len("data.pkl")]
      byteorder = "little"
      if f"{prefix}byteorder" in archive.namelist():
        byteorder = archive.read(_entry(archive, f"{prefix}byteorder", 16)).decode().strip()
        if byteorder not in ("little", "big"):
          raise _Refused(f"unknown byteorder {byteorder[:16]!r}")
      reader = _Reader(archive, prefix, byteorder, path.stat().st_size)
      return reader.resolve(reader.load())
    except _Refused as e:
      raise TorchFileError(f"{path}: {e}") from None
    except Exception as e:  # a damaged archive or pickle
      raise TorchFileError(f"{path}: unreadable archive or pickle ({type(e).__name__}: "
                           f"{' '.join(str(e).split())[:200]})") from None
