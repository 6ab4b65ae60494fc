"""Reads PyTorch `.pt` files (the zip format of `torch.save`, PyTorch >= 1.6) without
torch, as numpy arrays.

A `.pt` file is a zip archive `<name>/data.pkl` (a pickle) plus one raw little- or
big-endian buffer per tensor storage, `<name>/data/<key>` (`<name>/byteorder` says
which; absent means little). The pickle rebuilds each tensor with
`torch._utils._rebuild_tensor_v2(storage, offset, size, stride, ...)`, the storage
named by a persistent id `("storage", torch.<Type>Storage, key, location, numel)`.

Unpickling is restricted: only the globals in `_GLOBALS` (OrderedDict, the tensor and
parameter rebuild functions, the storage types) can be named; any other global, e.g.
a pickled class of some training script, raises `TorchFileError` before anything is
called. No code from the file is executed.
"""

import collections
import pickle
import zipfile
from pathlib import Path

import numpy as np


class TorchFileError(ValueError):
  """A file that is not a readable plain-tensor `.pt` archive."""


def _bfloat16(raw: np.ndarray) -> np.ndarray:
  return (raw.astype(np.uint32) << 16).view(np.float32)


# torch storage type -> (numpy dtype of the raw buffer, conversion or None)
_STORAGES = {
    "FloatStorage": (np.float32, None), "DoubleStorage": (np.float64, None),
    "HalfStorage": (np.float16, None), "BFloat16Storage": (np.uint16, _bfloat16),
    "LongStorage": (np.int64, None), "IntStorage": (np.int32, None),
    "ShortStorage": (np.int16, None), "CharStorage": (np.int8, None),
    "ByteStorage": (np.uint8, None), "BoolStorage": (np.bool_, None),
}


class _StorageType:
  """Stands for a torch storage class in a persistent id."""

  def __init__(self, name: str):
    self.name = name


class _Storage:
  """One storage buffer: a flat numpy array of `numel` elements."""

  def __init__(self, data: np.ndarray):
    self.data = data


def _rebuild_tensor(storage, offset, size, stride, requires_grad=False, hooks=None,
                    metadata=None):
  del requires_grad, hooks, metadata
  data = storage.data
  size, stride = tuple(size), tuple(stride)
  last = offset + sum((n - 1) * s for n, s in zip(size, stride)) if all(size) else offset
  if offset < 0 or any(s < 0 for s in stride) or (all(size) and last >= data.size):
    raise TorchFileError(f"tensor of size {size}, stride {stride}, offset {offset} "
                         f"exceeds its storage of {data.size} elements")
  view = np.lib.stride_tricks.as_strided(
      data[offset:], shape=size, strides=[s * data.itemsize for s in stride], writeable=False)
  return np.array(view)


def _rebuild_parameter(data, requires_grad=False, hooks=None, state=None):
  del requires_grad, hooks, state
  return data


_GLOBALS = {
    ("collections", "OrderedDict"): collections.OrderedDict,
    ("torch._utils", "_rebuild_tensor_v2"): _rebuild_tensor,
    ("torch._utils", "_rebuild_parameter"): _rebuild_parameter,
    ("torch._utils", "_rebuild_parameter_with_state"): _rebuild_parameter,
    **{("torch", name): _StorageType(name) for name in _STORAGES},
}


class _Unpickler(pickle.Unpickler):

  def __init__(self, file, archive: zipfile.ZipFile, prefix: str, byteorder: str, where: str):
    super().__init__(file)
    self._archive, self._prefix, self._byteorder, self._where = (archive, prefix, byteorder,
                                                                 where)
    self._storages = {}

  def find_class(self, module, name):
    try:
      return _GLOBALS[(module, name)]
    except KeyError:
      raise TorchFileError(
          f"{self._where}: the pickle names {module}.{name}, which is not a tensor, parameter "
          "or plain container; only state dicts of tensors (possibly inside dicts) are read"
      ) from None

  def persistent_load(self, pid):
    if not (isinstance(pid, tuple) and len(pid) == 5 and pid[0] == "storage"
            and isinstance(pid[1], _StorageType)):
      raise TorchFileError(f"{self._where}: unsupported persistent id {pid!r}")
    _, storage_type, key, _, numel = pid
    if key not in self._storages:
      dtype, convert = _STORAGES[storage_type.name]
      name = f"{self._prefix}data/{key}"
      try:
        raw = self._archive.read(name)
      except KeyError:
        raise TorchFileError(f"{self._where}: storage {name} missing from the archive") from None
      dtype = np.dtype(dtype).newbyteorder("<" if self._byteorder == "little" else ">")
      if len(raw) < numel * dtype.itemsize:
        raise TorchFileError(f"{self._where}: storage {name} holds {len(raw)} bytes, "
                             f"expected {numel * dtype.itemsize}")
      data = np.frombuffer(raw, dtype, count=numel).astype(dtype.newbyteorder("="))
      self._storages[key] = _Storage(convert(data) if convert else data)
    return self._storages[key]


def read_pt(path: str | Path):
  """The object a `torch.save` zip file holds, tensors as numpy arrays.

  Raises:
    TorchFileError: not a zip `.pt` file (e.g. the legacy pre-1.6 format), or its
      pickle names anything but containers, tensors and parameters.
  """
  path = Path(path)
  try:
    archive = zipfile.ZipFile(path)
  except (OSError, zipfile.BadZipFile) as e:
    raise TorchFileError(f"{path}: not a PyTorch zip checkpoint ({e}); files of "
                         "torch.save(..., _use_new_zipfile_serialization=False) are not read")
  with archive:
    pickles = [n for n in archive.namelist() if n.endswith("data.pkl") and n.count("/") == 1]
    if len(pickles) != 1:
      raise TorchFileError(f"{path}: expected one <name>/data.pkl in the archive, "
                           f"found {pickles}")
    prefix = pickles[0][:-len("data.pkl")]
    byteorder = "little"
    if f"{prefix}byteorder" in archive.namelist():
      byteorder = archive.read(f"{prefix}byteorder").decode().strip()
      if byteorder not in ("little", "big"):
        raise TorchFileError(f"{path}: unknown byteorder {byteorder!r}")
    with archive.open(pickles[0]) as f:
      try:
        return _Unpickler(f, archive, prefix, byteorder, str(path)).load()
      except TorchFileError:
        raise
      except Exception as e:
        raise TorchFileError(f"{path}: unreadable pickle ({type(e).__name__}: {e})") from e
