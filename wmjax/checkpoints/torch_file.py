"""PyTorch ``.pt`` files read without PyTorch, and without running anything they name.

``torch.save`` (PyTorch >= 1.6) writes a zip archive: ``<name>/data.pkl`` pickles the saved
object, in which a tensor is the call ``torch._utils._rebuild_tensor_v2(storage, offset, size,
stride, ...)`` and a storage the persistent id ``('storage', torch.FloatStorage, key, location,
numel)`` of the raw bytes in ``<name>/data/<key>`` (in the byte order ``<name>/byteorder`` names,
little-endian when absent). :func:`load` unpickles ``data.pkl`` with an unpickler that imports
nothing: dicts, lists, tuples and ``OrderedDict`` are Python's own, a tensor becomes a
:class:`StoredTensor` whose data are read from the archive only when :meth:`StoredTensor.numpy`
is called (so reading one state dict of a checkpoint does not read the others), and an object of
any other class (an optimiser's, a training script's config) an inert :class:`Opaque` record of
its class name and pickled arguments. No code named in the file runs.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import functools
import os
import pickle
import zipfile
from typing import Any, Iterator

import jax.numpy as jnp
import numpy as np

# torch's typed storage classes -> the numpy dtype of their elements
STORAGE_DTYPES = {
    "FloatStorage": np.float32, "DoubleStorage": np.float64, "HalfStorage": np.float16,
    "BFloat16Storage": jnp.bfloat16, "LongStorage": np.int64, "IntStorage": np.int32,
    "ShortStorage": np.int16, "CharStorage": np.int8, "ByteStorage": np.uint8,
    "BoolStorage": np.bool_,
}
# what torch.save writes before 1.6 (a pickled magic number), instead of a zip archive
LEGACY_MAGIC = b"\x80\x02\x8a\x0al\xfc\x9cF\xf9 j\xa8P\x19"


class TorchFileError(ValueError):
  """A file that is not a ``torch.save`` archive this reader can read, with the reason."""


class Opaque:
  """An object of a class the reader does not import: its ``name`` (``module.Class``) and what
  the pickle gave it (constructor ``args``, ``state``, ``items`` / ``entries`` appended or set).
  Nothing of the class runs; the object is a record to show, never to use."""

  name = "?"

  def __new__(cls, *args, **kwargs):
    del kwargs
    obj = super().__new__(cls)
    obj.args, obj.state, obj.items, obj.entries = args, None, [], {}
    return obj

  def __init__(self, *args, **kwargs):
    del args, kwargs

  def __setstate__(self, state):
    self.state = state

  def __setitem__(self, key, value):
    self.entries[key] = value

  def append(self, value):
    self.items.append(value)

  def extend(self, values):
    self.items.extend(values)

  def __repr__(self):
    return f"<{self.name}, not read>"


@functools.cache
def _opaque_class(module: str, name: str) -> type:
  return type(name, (Opaque,), {"name": f"{module}.{name}"})


@dataclasses.dataclass(frozen=True)
class _Storage:
  """One storage of an archive: its entry and element type (``dtype`` None: a storage class
  this reader does not know, named by ``kind``)."""

  archive: zipfile.ZipFile
  entry: str
  kind: str
  dtype: np.dtype | None
  numel: int

  def elements(self) -> np.ndarray:
    """The storage's elements, ``[numel]``."""
    if self.dtype is None:
      raise TorchFileError(f"a tensor is stored as {self.kind}, which this reader does not read "
                           f"(it reads {', '.join(STORAGE_DTYPES)})")
    try:
      data = self.archive.read(self.entry)
    except KeyError:
      raise TorchFileError(f"the archive lacks {self.entry}, which a tensor names") from None
    if len(data) != self.numel * self.dtype.itemsize:
      raise TorchFileError(f"{self.entry} holds {len(data)} bytes, not the {self.numel} "
                           f"elements of {self.dtype} its tensors name")
    return np.frombuffer(data, self.dtype)


@dataclasses.dataclass(frozen=True)
class StoredTensor:
  """A tensor of a ``.pt`` file, not yet read: ``shape``, ``dtype``, and where it lies in its
  storage (``offset`` and ``stride`` in elements)."""

  storage: _Storage
  offset: int
  shape: tuple[int, ...]
  stride: tuple[int, ...]

  @property
  def dtype(self) -> np.dtype | None:
    return self.storage.dtype

  def numpy(self) -> np.ndarray:
    """The tensor's values, ``shape`` and ``dtype`` (a copy), read from the archive, which must
    still be open (inside :func:`load`'s ``with``)."""
    elements = self.storage.elements()
    if 0 in self.shape:
      return np.zeros(self.shape, elements.dtype)
    last = self.offset + sum((n - 1) * s for n, s in zip(self.shape, self.stride))
    if self.offset < 0 or min(self.stride, default=0) < 0 or last >= elements.size:
      raise TorchFileError(f"a tensor of shape {self.shape} (offset {self.offset}, stride "
                           f"{self.stride}) reaches past its storage {self.storage.entry} of "
                           f"{elements.size} elements")
    itemsize = elements.dtype.itemsize
    view = np.lib.stride_tricks.as_strided(elements[self.offset:], self.shape,
                                           tuple(s * itemsize for s in self.stride))
    return np.array(view)


def _rebuild_tensor(storage, offset, shape, stride, *rest) -> StoredTensor:
  """torch's ``_rebuild_tensor_v2(storage, offset, size, stride, requires_grad, hooks[,
  metadata])``: the tensor, not read."""
  del rest
  if not isinstance(storage, _Storage):
    raise TorchFileError(f"a tensor's storage is {storage!r}, not one of the archive's")
  if len(shape) != len(stride) or min(shape, default=0) < 0:
    raise TorchFileError(f"a tensor's shape {shape} and stride {stride} do not agree")
  return StoredTensor(storage, int(offset), tuple(int(n) for n in shape),
                      tuple(int(s) for s in stride))


def _rebuild_parameter(data, *rest):
  """torch's ``_rebuild_parameter[_with_state](data, requires_grad, hooks[, state])``: the data."""
  del rest
  return data


@dataclasses.dataclass(frozen=True)
class _StorageType:
  """A storage class named in the pickle (``torch.FloatStorage``): only ever data."""

  kind: str


# the only names the unpickler resolves to something other than an Opaque class
_KNOWN = {
    ("collections", "OrderedDict"): collections.OrderedDict,
    ("torch._utils", "_rebuild_tensor_v2"): _rebuild_tensor,
    ("torch._utils", "_rebuild_parameter"): _rebuild_parameter,
    ("torch._utils", "_rebuild_parameter_with_state"): _rebuild_parameter,
}


class _Unpickler(pickle.Unpickler):
  """``data.pkl``'s unpickler: tensors and storages from ``archive`` under ``prefix``, inert
  records for every class it does not know, nothing imported."""

  def __init__(self, file, archive: zipfile.ZipFile, prefix: str, byteorder: str):
    super().__init__(file)
    self.archive, self.prefix, self.byteorder = archive, prefix, byteorder

  def find_class(self, module: str, name: str) -> Any:
    if (module, name) in _KNOWN:
      return _KNOWN[module, name]
    if module == "torch" and name.endswith("Storage"):
      return _StorageType(name)
    return _opaque_class(module, name)

  def persistent_load(self, pid: Any) -> _Storage:
    if not (isinstance(pid, tuple) and len(pid) == 5 and pid[0] == "storage"):
      raise TorchFileError(f"the pickle names {pid!r}, not a storage")
    _, kind, key, _, numel = pid
    kind = kind.kind if isinstance(kind, _StorageType) else getattr(kind, "name", repr(kind))
    dtype = STORAGE_DTYPES.get(kind)
    if dtype is not None:
      dtype = np.dtype(dtype)
      dtype = dtype.newbyteorder(">") if self.byteorder == "big" else dtype
    return _Storage(self.archive, f"{self.prefix}data/{key}", kind, dtype, int(numel))


def _pickle_entry(archive: zipfile.ZipFile) -> str:
  """The archive's one ``data.pkl`` (``<name>/data.pkl``)."""
  entries = [n for n in archive.namelist() if n == "data.pkl" or n.endswith("/data.pkl")]
  if len(entries) != 1:
    raise TorchFileError(f"a zip archive with {len(entries)} data.pkl entries, not what "
                         f"torch.save writes (one)")
  return entries[0]


def _byteorder(archive: zipfile.ZipFile, prefix: str) -> str:
  try:
    order = archive.read(f"{prefix}byteorder").decode().strip()
  except KeyError:
    return "little"  # torch writes no byteorder entry on little-endian machines before 2.1
  if order not in ("little", "big"):
    raise TorchFileError(f"{prefix}byteorder says {order!r}, not 'little' or 'big'")
  return order


def _open_archive(path: str) -> zipfile.ZipFile:
  if not os.path.isfile(path):
    raise FileNotFoundError(f"no file at {path}")
  if zipfile.is_zipfile(path):
    return zipfile.ZipFile(path)
  with open(path, "rb") as f:
    head = f.read(len(LEGACY_MAGIC))
  if head == LEGACY_MAGIC:
    raise TorchFileError("a file in PyTorch's serialization from before 1.6, which this reader "
                         "does not read; saved again by a newer PyTorch (torch.save(torch.load("
                         "f), f)) it reads")
  raise TorchFileError("not a PyTorch file: torch.save writes a zip archive")


@contextlib.contextmanager
def load(path: str) -> Iterator[Any]:
  """The object ``torch.save`` wrote to ``path``, with each tensor a :class:`StoredTensor` and
  each object of another class an :class:`Opaque` record; tensors read while the ``with`` lasts:

    with torch_file.load("ckpt.pt") as checkpoint:
      weights = {k: v.numpy() for k, v in checkpoint["ema"].items()}

  A file that is not such an archive, or a pickle that breaks off, raises
  :class:`TorchFileError`."""
  with _open_archive(path) as archive:
    entry = _pickle_entry(archive)
    prefix = entry[:-len("data.pkl")]
    byteorder = _byteorder(archive, prefix)
    with archive.open(entry) as f:
      try:
        obj = _Unpickler(f, archive, prefix, byteorder).load()
      except TorchFileError:
        raise
      except Exception as e:  # whatever a damaged or foreign pickle makes the unpickler raise
        raise TorchFileError(f"its data.pkl does not unpickle: {type(e).__name__}: {e}") from e
    yield obj
