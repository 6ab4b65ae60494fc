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
  and tensors; containers nested deeper than `torch_tensors.MAX_DEPTH`, or cyclic; more than
  `torch_tensors.MAX_OBJECTS` containers and tensors;
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
import pickle
import zipfile
from pathlib import Path

import numpy as np

from cvmdx_jax.errors import UserError
from cvmdx_jax.models.torch_tensors import (
    SCALARS,
    STORAGES,
    Refused,
    StorageRef,
    StorageType,
    TensorArgs,
    TensorBuilder,
    describe,
    is_int,
)

MAX_PICKLE_BYTES = 1 << 19  # ~4,500 tensors; the official U-Net's (227 tensors) is 26 kB


class TorchFileError(UserError):
  """A file that is not a readable plain-tensor `.pt` archive."""


_OPCODES = (
    "PROTO FRAME STOP MARK POP POP_MARK DUP NONE NEWTRUE NEWFALSE INT BININT BININT1 BININT2 "
    "LONG LONG1 LONG4 FLOAT BINFLOAT STRING BINSTRING SHORT_BINSTRING UNICODE BINUNICODE "
    "SHORT_BINUNICODE BINUNICODE8 BINBYTES SHORT_BINBYTES BINBYTES8 EMPTY_TUPLE TUPLE TUPLE1 "
    "TUPLE2 TUPLE3 EMPTY_LIST LIST APPEND APPENDS EMPTY_DICT SETITEM SETITEMS GET BINGET "
    "LONG_BINGET PUT BINPUT LONG_BINPUT MEMOIZE GLOBAL STACK_GLOBAL REDUCE BUILD BINPERSID"
).split()


def _entry(archive: zipfile.ZipFile, name: str, limit: int) -> zipfile.ZipInfo:
  """The header of entry `name`, checked: stored uncompressed, at most `limit` bytes."""
  try:
    info = archive.getinfo(name)
  except KeyError:
    raise Refused(f"entry {name} missing from the archive") from None
  if info.compress_type != zipfile.ZIP_STORED:
    raise Refused(
        f"entry {name} is compressed (method {info.compress_type}); torch.save "
        "stores entries uncompressed"
    )
  if info.file_size != info.compress_size:
    raise Refused(
        f"entry {name} declares {info.file_size} bytes but stores " f"{info.compress_size}"
    )
  if info.file_size > limit:
    raise Refused(f"entry {name} declares {info.file_size} bytes, more than the {limit} " "allowed")
  return info


class _Dispatch(dict):
  """The opcode table: a missing opcode is refused (nothing is inserted)."""

  def __missing__(self, opcode: int):
    raise Refused(
        f"the pickle uses opcode {bytes([opcode])!r}, outside those of plain "
        "containers and tensors (object construction, extensions, sets, buffers)"
    )


class _Reader(pickle._Unpickler):  # the Python VM, so that opcodes can be restricted
  """One read of one archive's pickle: the restricted unpickler (tensors stay
  `TensorArgs` until the `TensorBuilder` checks and builds them)."""

  def __init__(self, archive: zipfile.ZipFile, prefix: str, byteorder: str, length: int):
    del byteorder  # the storages' bytes are read by the `TensorBuilder`
    self._archive, self._prefix, self._length = archive, prefix, length
    self._unread = length  # bytes the entries still read may add up to
    self._types = {name: StorageType(name) for name in STORAGES}
    self._rebuilds = (self._rebuild_tensor, self._rebuild_parameter, collections.OrderedDict)
    self._globals = {
        ("collections", "OrderedDict"): collections.OrderedDict,
        ("torch._utils", "_rebuild_tensor_v2"): self._rebuilds[0],
        ("torch._utils", "_rebuild_parameter"): self._rebuilds[1],
        ("torch._utils", "_rebuild_parameter_with_state"): self._rebuilds[1],
        **{("torch", name): t for name, t in self._types.items()},
    }
    self._refs = {}
    pkl = _entry(archive, f"{prefix}data.pkl", MAX_PICKLE_BYTES)
    super().__init__(io.BytesIO(self.read_entry(pkl)))

  def read_entry(self, info: zipfile.ZipInfo) -> bytes:
    """The bytes of entry `info`, counted against the archive's length."""
    self._unread -= info.file_size
    if self._unread < 0:
      raise Refused(
          f"entry {info.filename}: the entries read add up to more than the "
          f"archive's {self._length} bytes"
      )
    return self._archive.read(info)

  # ------------------------------------------------------------- the pickle VM

  def find_class(self, module, name):
    try:
      return self._globals[(module, name)]
    except KeyError:
      raise Refused(
          f"the pickle names {module}.{name}, which is not a tensor, parameter or "
          "plain container; only state dicts of tensors (possibly inside dicts) "
          "are read"
      ) from None

  def persistent_load(self, pid):
    if not (
        type(pid) is tuple
        and len(pid) == 5
        and pid[0] == "storage"
        and any(pid[1] is t for t in self._types.values())
        and type(pid[2]) is str
        and is_int(pid[4])
        and pid[4] >= 0
    ):
      raise Refused(
          f"unsupported persistent id (a {describe(pid)}); expected ('storage', "
          "torch.<Type>Storage, key, location, numel)"
      )
    _, storage_type, key, _, numel = pid
    ref = self._refs.get(key)
    if ref is None:
      info = _entry(self._archive, f"{self._prefix}data/{key}", self._length)
      itemsize = np.dtype(STORAGES[storage_type.name][0]).itemsize
      if numel * itemsize > info.file_size:
        raise Refused(
            f"storage {info.filename} declares {numel} elements of "
            f"{storage_type.name} ({numel * itemsize} bytes), the entry holds "
            f"{info.file_size}"
        )
      ref = self._refs[key] = StorageRef(info, storage_type.name, numel)
    if (ref.kind, ref.numel) != (storage_type.name, numel):
      raise Refused(
          f"storage {ref.info.filename} is named as {ref.kind} of {ref.numel} "
          f"elements and as {storage_type.name} of {numel}"
      )
    return ref

  def _rebuild_tensor(self, storage, offset, size, stride, *unused):
    del unused  # requires_grad, backward hooks, metadata
    if type(storage) is not StorageRef:
      raise Refused(f"a tensor rebuilt from {describe(storage)}, not a storage")
    return TensorArgs(storage, offset, size, stride)

  def _rebuild_parameter(self, data, *unused):
    del unused
    if type(data) is not TensorArgs:
      raise Refused(f"a parameter rebuilt from {describe(data)}, not a tensor")
    return data

  def _load_reduce(self):
    args = self.stack.pop()
    func = self.stack[-1]
    if not any(func is f for f in self._rebuilds) or type(args) is not tuple:
      raise Refused(
          f"REDUCE calls {describe(func)}; only tensor and parameter rebuilds are " "called"
      )
    if func is collections.OrderedDict and args:
      raise Refused("REDUCE calls OrderedDict with arguments")
    self.stack[-1] = func(*args)

  def _set_items(self, items):
    target = self.stack[-1]
    if type(target) not in (dict, collections.OrderedDict):
      raise Refused(f"SETITEM on {describe(target)}, not a dict")
    if len(items) % 2:
      raise Refused("SETITEMS with a key but no value")
    for key, value in zip(items[::2], items[1::2]):
      if not isinstance(key, SCALARS):
        raise Refused(f"a dict key of type {describe(key)}; keys are numbers or strings")
      target[key] = value

  def _append_items(self, items):
    target = self.stack[-1]
    if type(target) is not list:
      raise Refused(f"APPEND on {describe(target)}, not a list")
    target.extend(items)

  def _load_build(self):
    state = self.stack.pop()
    target = self.stack[-1]
    if type(target) is not collections.OrderedDict or type(state) is not dict:
      raise Refused(
          f"BUILD sets the state of {describe(target)}; only an OrderedDict's "
          "attributes are read (and dropped)"
      )

  dispatch = _Dispatch(
      {op: pickle._Unpickler.dispatch[op] for op in (getattr(pickle, name)[0] for name in _OPCODES)}
  )
  dispatch.update(
      {
          pickle.REDUCE[0]: _load_reduce,
          pickle.BUILD[0]: _load_build,
          pickle.SETITEM[0]: lambda self: self._set_items([self.stack.pop(-2), self.stack.pop()]),
          pickle.SETITEMS[0]: lambda self: self._set_items(self.pop_mark()),
          pickle.APPEND[0]: lambda self: self._append_items([self.stack.pop()]),
          pickle.APPENDS[0]: lambda self: self._append_items(self.pop_mark()),
      }
  )


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
    raise TorchFileError(
        f"{path}: not a PyTorch zip checkpoint ({type(e).__name__}: "
        f"{str(e)[:200]}); files of torch.save(..., "
        "_use_new_zipfile_serialization=False) are not read"
    ) from None
  with archive:
    try:
      pickles = [n for n in archive.namelist() if n.endswith("/data.pkl") and n.count("/") == 1]
      if len(pickles) != 1:
        raise Refused(f"expected one <name>/data.pkl in the archive, found {pickles[:4]}")
      prefix = pickles[0][: -len("data.pkl")]
      byteorder = "little"
      if f"{prefix}byteorder" in archive.namelist():
        byteorder = archive.read(_entry(archive, f"{prefix}byteorder", 16)).decode().strip()
        if byteorder not in ("little", "big"):
          raise Refused(f"unknown byteorder {byteorder[:16]!r}")
      length = path.stat().st_size
      reader = _Reader(archive, prefix, byteorder, length)
      tree = reader.load()
      return TensorBuilder(reader.read_entry, byteorder, length).resolve(tree)
    except Refused as e:
      raise TorchFileError(f"{path}: {e}") from None
    except Exception as e:  # a damaged archive or pickle
      raise TorchFileError(
          f"{path}: unreadable archive or pickle ({type(e).__name__}: "
          f"{' '.join(str(e).split())[:200]})"
      ) from None
