"""Read a PyTorch ``state_dict`` written by ``torch.save`` into NumPy arrays, without torch.

A ``.pt`` file in torch's zip format (the default since torch 1.6) holds ``<prefix>/data.pkl``,
a pickle whose tensors are calls to ``torch._utils._rebuild_tensor_v2`` over storages that
``persistent_load`` fetches from the raw records ``<prefix>/data/<key>``. Unpickling can run
arbitrary code, so the unpickler here resolves only an allowlist of globals, each to a local
stand-in; torch is never imported.

One module on purpose: a self-contained reader of one foreign file format (the allowlisted
unpickler, the storage records and the tensor views belong together); nothing else in the
library depends on its internals.
"""

from __future__ import annotations

import collections
import io
import os
import pickle
import sys
import zipfile
import zlib
from collections.abc import Mapping
from typing import Any, NamedTuple

import numpy as np

from jaxinertia.errors import WeightsError

__all__ = ["StateDictError", "UnsupportedPickleError", "load_state_dict"]


class StateDictError(WeightsError):
    """The file is not a state dict of tensors that this module can read."""


class UnsupportedPickleError(StateDictError):
    """``data.pkl`` references a global outside the allowlist."""

    def __init__(self, path: str, global_name: str) -> None:
        super().__init__(
            f"{path}: data.pkl references the global {global_name!r}, which a plain state dict "
            "of tensors does not need; refusing to unpickle it (unpickling arbitrary globals "
            "can run code)"
        )
        self.path = path
        self.global_name = global_name


# Stand-ins are NamedTuples: immutable and without __dict__, so a hostile pickle cannot use
# BUILD to alter the shared module-level instances for later loads.
class _TorchDtype(NamedTuple):
    name: str  # torch's name, as a pickled dtype global spells it (torch.<name>)
    itemsize: int
    from_ml_dtypes: bool  # NumPy lacks the type; ml_dtypes names it like torch does


class _StorageType(NamedTuple):
    name: str
    dtype: _TorchDtype


class _Storage(NamedTuple):
    key: str
    record: str
    dtype: _TorchDtype


class _TensorRef(NamedTuple):
    # Arrays are built after unpickling, once the state-dict key is known for error messages.
    storage: _Storage
    dtype: _TorchDtype
    offset: Any
    size: Any
    stride: Any
    metadata: Any


_DTYPES: dict[str, _TorchDtype] = {
    d.name: d
    for d in (
        _TorchDtype("float64", 8, False),
        _TorchDtype("float32", 4, False),
        _TorchDtype("float16", 2, False),
        _TorchDtype("bfloat16", 2, True),
        _TorchDtype("float8_e4m3fn", 1, True),
        _TorchDtype("float8_e5m2", 1, True),
        _TorchDtype("float8_e4m3fnuz", 1, True),
        _TorchDtype("float8_e5m2fnuz", 1, True),
        _TorchDtype("complex128", 16, False),
        _TorchDtype("complex64", 8, False),
        _TorchDtype("int64", 8, False),
        _TorchDtype("int32", 4, False),
        _TorchDtype("int16", 2, False),
        _TorchDtype("int8", 1, False),
        _TorchDtype("uint64", 8, False),
        _TorchDtype("uint32", 4, False),
        _TorchDtype("uint16", 2, False),
        _TorchDtype("uint8", 1, False),
        _TorchDtype("bool", 1, False),
    )
}

_STORAGE_TYPES: dict[str, _StorageType] = {
    name: _StorageType(name, _DTYPES[dtype])
    for name, dtype in (
        ("DoubleStorage", "float64"),
        ("FloatStorage", "float32"),
        ("HalfStorage", "float16"),
        ("BFloat16Storage", "bfloat16"),
        ("ComplexDoubleStorage", "complex128"),
        ("ComplexFloatStorage", "complex64"),
        ("LongStorage", "int64"),
        ("IntStorage", "int32"),
        ("ShortStorage", "int16"),
        ("CharStorage", "int8"),
        ("ByteStorage", "uint8"),
        ("BoolStorage", "bool"),
        # Untyped storages are bytes; _rebuild_tensor_v3 passes the element dtype separately.
        ("UntypedStorage", "uint8"),
    )
}

# torch.save(..., _use_new_zipfile_serialization=False) and torch < 1.6 write a bare pickle
# stream that starts with this magic number.
_LEGACY_MAGIC = b"\x80\x02\x8a\x0a" + (0x1950A86A20F9469CFC6C).to_bytes(10, "little")

# Exceptions that a malformed (rather than hostile) data.pkl raises inside pickle.load.
_PICKLE_ERRORS = (
    pickle.UnpicklingError,
    EOFError,
    TypeError,
    ValueError,
    AttributeError,
    IndexError,
    KeyError,
    RecursionError,
)


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


class _StateDictUnpickler(pickle.Unpickler):
    def __init__(self, data: bytes, *, path: str, archive: zipfile.ZipFile, prefix: str) -> None:
        super().__init__(io.BytesIO(data))
        self._path = path
        self._archive = archive
        self._prefix = prefix
        self._storages: dict[str, _Storage] = {}
        # Bound methods: unlike plain functions, BUILD cannot set their __defaults__.
        self._rebuilders = {
            "torch._utils._rebuild_tensor_v2": self._rebuild_tensor_v2,
            "torch._utils._rebuild_tensor_v3": self._rebuild_tensor_v3,
            "torch._utils._rebuild_parameter": self._rebuild_parameter,
            "torch._utils._rebuild_parameter_with_state": self._rebuild_parameter_with_state,
        }

    def find_class(self, module: str, name: str) -> Any:
        qualname = f"{module}.{name}"
        if qualname == "collections.OrderedDict":
            # The real class: a C type whose attributes BUILD cannot overwrite.
            return collections.OrderedDict
        if qualname in self._rebuilders:
            return self._rebuilders[qualname]
        if module == "torch" and name in _STORAGE_TYPES:
            return _STORAGE_TYPES[name]
        if module == "torch" and name in _DTYPES:
            return _DTYPES[name]
        raise UnsupportedPickleError(self._path, qualname)

    def persistent_load(self, pid: Any) -> _Storage:
        if not (isinstance(pid, tuple) and len(pid) == 5 and pid[0] == "storage"):
            raise StateDictError(f"{self._path}: unsupported persistent id {pid!r:.100}")
        # The location ('cpu', 'cuda:0') only says where torch would put the storage.
        _, storage_type, key, _location, numel = pid
        if not (isinstance(storage_type, _StorageType) and isinstance(key, str) and _is_int(numel)):
            raise StateDictError(f"{self._path}: malformed storage id {pid!r:.100}")
        # Views and tied weights share one storage; torch pickles it once per key.
        if key in self._storages:
            return self._storages[key]
        record = f"{self._prefix}/data/{key}"
        try:
            info = self._archive.getinfo(record)
        except KeyError:
            raise StateDictError(
                f"{self._path}: storage record {record!r} (storage key {key!r}) is missing"
            ) from None
        nbytes = numel * storage_type.dtype.itemsize
        if numel < 0 or info.file_size != nbytes:
            raise StateDictError(
                f"{self._path}: storage record {record!r} holds {info.file_size} bytes, but its "
                f"id says {numel} x {storage_type.name} = {nbytes} bytes"
            )
        storage = _Storage(key, record, storage_type.dtype)
        self._storages[key] = storage
        return storage

    def _rebuild_tensor_v2(
        self,
        storage: Any,
        storage_offset: Any,
        size: Any,
        stride: Any,
        requires_grad: Any,
        backward_hooks: Any,
        metadata: Any = None,
    ) -> _TensorRef:
        if not isinstance(storage, _Storage):
            raise StateDictError(f"{self._path}: _rebuild_tensor_v2 got no storage")
        return _TensorRef(storage, storage.dtype, storage_offset, size, stride, metadata)

    def _rebuild_tensor_v3(
        self,
        storage: Any,
        storage_offset: Any,
        size: Any,
        stride: Any,
        requires_grad: Any,
        backward_hooks: Any,
        dtype: Any,
        metadata: Any = None,
    ) -> _TensorRef:
        # torch >= 2.1 uses v3 for dtypes without a typed storage class (uint16, float8, ...):
        # an untyped storage whose bytes are read as `dtype`, offset and strides in elements.
        if not isinstance(storage, _Storage) or not isinstance(dtype, _TorchDtype):
            raise StateDictError(f"{self._path}: _rebuild_tensor_v3 got no storage or dtype")
        return _TensorRef(storage, dtype, storage_offset, size, stride, metadata)

    def _rebuild_parameter(self, data: Any, requires_grad: Any, backward_hooks: Any) -> Any:
        return data

    def _rebuild_parameter_with_state(
        self, data: Any, requires_grad: Any, backward_hooks: Any, state: Any
    ) -> Any:
        # The state holds Python attributes of the Parameter object, not values.
        return data


def _read_record(archive: zipfile.ZipFile, path: str, record: str) -> bytes:
    try:
        return archive.read(record)
    except KeyError:
        raise StateDictError(f"{path}: record {record!r} is missing") from None
    except (zipfile.BadZipFile, zlib.error, NotImplementedError, EOFError, OSError) as err:
        raise StateDictError(f"{path}: cannot read record {record!r}: {err}") from err


def _find_prefix(archive: zipfile.ZipFile, path: str) -> str:
    # torch names the top folder "archive" (torch >= 2) or after the file's stem (older).
    prefixes = [
        name.removesuffix("/data.pkl")
        for name in archive.namelist()
        if name.endswith("/data.pkl") and name.count("/") == 1
    ]
    if not prefixes:
        raise StateDictError(f"{path}: no '<prefix>/data.pkl' record; not a torch.save archive")
    if len(prefixes) > 1:
        raise StateDictError(f"{path}: several data.pkl records ({prefixes}); which is meant?")
    return prefixes[0]


def _read_byteorder(archive: zipfile.ZipFile, path: str, prefix: str) -> str:
    record = f"{prefix}/byteorder"
    if record not in archive.namelist():
        # torch < 1.13 wrote no byteorder record; those files came from little-endian hosts.
        return "little"
    order = _read_record(archive, path, record).decode("ascii", errors="replace").strip()
    if order not in ("little", "big"):
        raise StateDictError(f"{path}: record {record!r} says {order!r}, not 'little' or 'big'")
    return order


def _numpy_dtype(dtype: _TorchDtype, path: str, key: str) -> np.dtype:
    if not dtype.from_ml_dtypes:
        return np.dtype(dtype.name)
    try:  # optional: only the bfloat16/float8 tensors need it (it ships with jax)
        import ml_dtypes
    except ImportError:
        raise StateDictError(
            f"{path}: tensor {key!r} has dtype torch.{dtype.name}, which NumPy lacks; "
            "install ml_dtypes to load it"
        ) from None
    scalar_type = getattr(ml_dtypes, dtype.name, None)
    if scalar_type is None:
        raise StateDictError(
            f"{path}: tensor {key!r} has dtype torch.{dtype.name}, which this ml_dtypes "
            f"({ml_dtypes.__version__}) lacks"
        )
    return np.dtype(scalar_type)


def _decode(raw: bytes, dtype: np.dtype, byteorder: str) -> np.ndarray:
    if byteorder == sys.byteorder or dtype.itemsize == 1:
        return np.frombuffer(raw, dtype=dtype)
    # ml_dtypes' types cannot be byte-swapped by NumPy, so swap unsigned words of the same
    # size; complex numbers swap each component, as torch does.
    unit = dtype.itemsize // 2 if dtype.kind == "c" else dtype.itemsize
    stored = np.dtype(f"u{unit}").newbyteorder(">" if byteorder == "big" else "<")
    return np.frombuffer(raw, dtype=stored).astype(f"u{unit}").view(dtype)


def _materialize(ref: _TensorRef, key: str, path: str, raw: bytes, byteorder: str) -> np.ndarray:
    where = f"{path}: tensor {key!r} (storage record {ref.storage.record!r})"
    size, stride, offset = ref.size, ref.stride, ref.offset
    if not (
        isinstance(size, tuple)
        and isinstance(stride, tuple)
        and len(size) == len(stride)
        and all(_is_int(n) and n >= 0 for n in size)
        and all(_is_int(s) and s >= 0 for s in stride)
        and _is_int(offset)
        and offset >= 0
    ):
        raise StateDictError(
            f"{where}: malformed offset/size/stride {offset!r:.40}/{size!r:.80}/{stride!r:.80}"
        )
    dtype = _numpy_dtype(ref.dtype, path, key)
    if len(raw) % dtype.itemsize:
        raise StateDictError(f"{where}: {len(raw)} bytes is no whole number of {dtype} items")
    flat = _decode(raw, dtype, byteorder)
    if 0 in size:
        array = np.empty(size, dtype=dtype)
    else:
        # as_strided reads whatever memory the strides point at, so bound them first.
        last = offset + sum((n - 1) * s for n, s in zip(size, stride, strict=True))
        if last >= flat.size:
            raise StateDictError(
                f"{where}: offset {offset}, size {size}, stride {stride} reach element {last} "
                f"of a storage of {flat.size}"
            )
        view = np.lib.stride_tricks.as_strided(
            flat[offset:],
            shape=size,
            strides=tuple(s * dtype.itemsize for s in stride),
            writeable=False,
        )
        array = view.copy(order="C")
    return _apply_metadata(array, ref.metadata, where)


def _apply_metadata(array: np.ndarray, metadata: Any, where: str) -> np.ndarray:
    # torch stores lazily negated/conjugated views unresolved and marks them with these keys;
    # torch sets the bit whenever the key is present, whatever its value.
    if metadata is None:
        return array
    if not isinstance(metadata, Mapping) or set(metadata) - {"conj", "neg"}:
        raise StateDictError(f"{where}: unsupported tensor metadata {metadata!r:.100}")
    if "neg" in metadata:
        if array.dtype == np.bool_:
            raise StateDictError(f"{where}: negated view of a bool tensor")
        array = np.negative(array)
    if "conj" in metadata:
        array = np.conj(array)
    return array


def _not_zip_message(path: str) -> str:
    message = f"{path}: not a zip archive, so not a torch.save file in the zip format"
    try:
        with open(path, "rb") as file:
            head = file.read(len(_LEGACY_MAGIC))
    except OSError:
        return message
    if head == _LEGACY_MAGIC:
        message += (
            " (it is torch's legacy format: load it with torch and save it again with a "
            "current torch.save)"
        )
    return message


def load_state_dict(path: str | os.PathLike[str]) -> dict[str, np.ndarray]:
    """Read ``torch.save(model.state_dict(), path)`` into C-contiguous arrays, in file order.

    Raises StateDictError when the file is unreadable or is not a state dict of tensors, and its
    subclass UnsupportedPickleError when data.pkl references a global outside the allowlist.
    """
    name = os.fspath(path)
    try:
        archive = zipfile.ZipFile(name)
    except zipfile.BadZipFile as err:
        raise StateDictError(_not_zip_message(name)) from err
    except OSError as err:
        raise StateDictError(f"{name}: cannot open: {err.strerror or err}") from err
    with archive:
        prefix = _find_prefix(archive, name)
        byteorder = _read_byteorder(archive, name, prefix)
        pickled = _read_record(archive, name, f"{prefix}/data.pkl")
        unpickler = _StateDictUnpickler(pickled, path=name, archive=archive, prefix=prefix)
        try:
            obj = unpickler.load()
        except StateDictError:
            raise
        except _PICKLE_ERRORS as err:
            raise StateDictError(f"{name}: malformed data.pkl: {err}") from err
        if not isinstance(obj, Mapping):
            raise StateDictError(f"{name}: data.pkl holds a {type(obj).__name__}, not a dict")
        raw: dict[str, bytes] = {}
        arrays: dict[str, np.ndarray] = {}
        for key, value in obj.items():
            if not isinstance(key, str):
                raise StateDictError(f"{name}: state-dict key {key!r:.80} is not a string")
            if not isinstance(value, _TensorRef):
                raise StateDictError(
                    f"{name}: entry {key!r} is a {type(value).__name__}, not a tensor"
                )
            record = value.storage.record
            if record not in raw:
                raw[record] = _read_record(archive, name, record)
            arrays[key] = _materialize(value, key, name, raw[record], byteorder)
    return arrays
