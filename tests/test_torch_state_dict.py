"""Tests for jaxinertia.torch_state_dict.

The reference is lbipe's own export of each checkpoint to .npz; synthetic archives, written
opcode by opcode so that neither side needs torch, cover views, byte order and hostile input.
"""

from __future__ import annotations

import os
import pickle
import struct
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
from support.asserts import difference

from jaxinertia.torch_state_dict import StateDictError, UnsupportedPickleError, load_state_dict

REPO = Path(__file__).resolve().parents[1]
LBIPE_HELP = (
    "set JAXINERTIA_LBIPE_DIR to a checkout of github.com/ChirikjianLab/lbipe "
    "or place it at ../shared/lbipe"
)
LBIPE_STEMS = [f"dict_{net}_{i}" for net in ("torque", "attn") for i in range(1, 11)]
# The reference, lbipe's own .npz export of each checkpoint, is matched byte for byte (keys
# in order, dtype, shape, layout, bits): no tolerance; a failure reports the difference.


@pytest.fixture(scope="module")
def lbipe_weights() -> Path:
    root = Path(os.environ.get("JAXINERTIA_LBIPE_DIR") or REPO.parent / "shared" / "lbipe")
    weights = root / "weights"
    if not weights.is_dir():
        message = f"lbipe weights not found at {weights}: {LBIPE_HELP}"
        if os.environ.get("CI"):
            pytest.fail(message)
        pytest.skip(message)
    return weights


@pytest.mark.parametrize("stem", LBIPE_STEMS)
def test_lbipe_checkpoint_matches_npz(lbipe_weights: Path, stem: str) -> None:
    pt, npz = lbipe_weights / f"{stem}.pt", lbipe_weights / f"{stem}.npz"
    assert pt.is_file() and npz.is_file(), f"{stem}: .pt or .npz missing in {lbipe_weights}"
    loaded = load_state_dict(pt)
    with np.load(npz) as expected:
        assert list(loaded) == expected.files, f"{stem}: keys or their order differ"
        for key, array in loaded.items():
            want = expected[key]
            assert array.dtype == want.dtype, f"{stem}[{key}]: dtype {array.dtype} != {want.dtype}"
            assert array.shape == want.shape, f"{stem}[{key}]: shape {array.shape} != {want.shape}"
            assert array.flags.c_contiguous and array.flags.writeable, f"{stem}[{key}]: layout"
            assert array.tobytes() == np.ascontiguousarray(want).tobytes(), (
                f"{stem}[{key}]: bits differ ({difference(array, want, equal_nan=False)})")


# --- synthetic archives -------------------------------------------------------------------------
# Protocol-2 opcodes, so the pickles name torch's globals without importing torch.


def _global(module: str, name: str) -> bytes:
    return b"c" + f"{module}\n{name}\n".encode()


def _str(text: str) -> bytes:
    data = text.encode()
    return b"X" + struct.pack("<I", len(data)) + data


def _int(value: int) -> bytes:
    return b"J" + struct.pack("<i", value)


def _tuple(*items: bytes) -> bytes:
    return b"(" + b"".join(items) + b"t"


def _call(func: bytes, *args: bytes) -> bytes:
    return func + _tuple(*args) + b"R"


def _storage(storage_type: str, key: str, numel: int) -> bytes:
    pid = _tuple(
        _str("storage"), _global("torch", storage_type), _str(key), _str("cpu"), _int(numel)
    )
    return pid + b"Q"


def _tensor(storage: bytes, offset: int, size: tuple[int, ...], stride: tuple[int, ...]) -> bytes:
    return _call(
        _global("torch._utils", "_rebuild_tensor_v2"),
        storage,
        _int(offset),
        _tuple(*map(_int, size)),
        _tuple(*map(_int, stride)),
        b"\x89",  # requires_grad=False
        _call(_global("collections", "OrderedDict")),  # backward hooks
    )


def _state_dict(entries: dict[str, bytes]) -> bytes:
    body = b"".join(_str(key) + value + b"s" for key, value in entries.items())
    return b"\x80\x02" + _call(_global("collections", "OrderedDict")) + body + b"."


def _write_pt(path: Path, pickled: bytes, records: dict[str, bytes], **extra: bytes) -> Path:
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("archive/data.pkl", pickled)
        for name, data in extra.items():
            archive.writestr(f"archive/{name}", data)
        for key, data in records.items():
            archive.writestr(f"archive/data/{key}", data)
    return path


def test_views_offsets_and_shared_storage(tmp_path: Path) -> None:
    base = np.arange(24, dtype=np.float64)
    storage = _storage("DoubleStorage", "0", base.size)
    pickled = _state_dict(
        {
            "transposed": _tensor(storage, 0, (3, 4), (1, 3)),
            "strided": _tensor(storage, 5, (2,), (3,)),
            "scalar": _tensor(storage, 23, (), ()),
            "empty": _tensor(storage, 0, (0, 3), (3, 1)),
        }
    )
    loaded = load_state_dict(_write_pt(tmp_path / "v.pt", pickled, {"0": base.tobytes()}))
    assert list(loaded) == ["transposed", "strided", "scalar", "empty"]
    np.testing.assert_array_equal(
        loaded["transposed"], base[np.add.outer(np.arange(3), 3 * np.arange(4))]
    )
    np.testing.assert_array_equal(loaded["strided"], base[[5, 8]])
    assert loaded["scalar"].shape == () and loaded["scalar"] == 23.0
    assert loaded["empty"].shape == (0, 3) and loaded["empty"].dtype == np.float64
    assert all(a.flags.c_contiguous for a in loaded.values())


def test_big_endian_archive(tmp_path: Path) -> None:
    ints = np.array([1, -2, 70000], dtype=np.int32)
    cplx = np.array([1 + 2j, -3.5j], dtype=np.complex64)
    pickled = _state_dict(
        {
            "i": _tensor(_storage("IntStorage", "0", 3), 0, (3,), (1,)),
            "c": _tensor(_storage("ComplexFloatStorage", "1", 2), 0, (2,), (1,)),
        }
    )
    records = {"0": ints.astype(">i4").tobytes(), "1": cplx.astype(">c8").tobytes()}
    loaded = load_state_dict(_write_pt(tmp_path / "be.pt", pickled, records, byteorder=b"big"))
    assert loaded["i"].dtype == np.dtype(np.int32)  # native order, as torch would give
    np.testing.assert_array_equal(loaded["i"], ints)
    np.testing.assert_array_equal(loaded["c"], cplx)


def test_bfloat16_and_v3_uint16(tmp_path: Path) -> None:
    ml_dtypes = pytest.importorskip("ml_dtypes", reason="bfloat16 needs ml_dtypes")
    bf16 = np.array([1.5, -0.0, 3e38], dtype=ml_dtypes.bfloat16)
    u16 = np.array([0, 65535, 4660], dtype=np.uint16)
    v3 = _call(
        _global("torch._utils", "_rebuild_tensor_v3"),
        _storage("UntypedStorage", "1", u16.nbytes),
        _int(1),
        _tuple(_int(2)),
        _tuple(_int(1)),
        b"\x89",
        _call(_global("collections", "OrderedDict")),
        _global("torch", "uint16"),
    )
    pickled = _state_dict(
        {"bf16": _tensor(_storage("BFloat16Storage", "0", 3), 0, (3,), (1,)), "u16": v3}
    )
    loaded = load_state_dict(
        _write_pt(tmp_path / "x.pt", pickled, {"0": bf16.tobytes(), "1": u16.tobytes()})
    )
    assert loaded["bf16"].dtype == np.dtype(ml_dtypes.bfloat16)
    assert loaded["bf16"].tobytes() == bf16.tobytes()
    assert loaded["u16"].dtype == np.uint16
    np.testing.assert_array_equal(loaded["u16"], u16[1:])


def test_does_not_import_torch(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "torch", None)  # any `import torch` now fails
    pickled = _state_dict({"w": _tensor(_storage("FloatStorage", "0", 2), 0, (2,), (1,))})
    path = _write_pt(tmp_path / "w.pt", pickled, {"0": np.ones(2, np.float32).tobytes()})
    np.testing.assert_array_equal(load_state_dict(path)["w"], np.ones(2, np.float32))


class _RunsShell:
    def __init__(self, command: str) -> None:
        self.command = command

    def __reduce__(self):
        return os.system, (self.command,)


def test_forbidden_global_is_refused_and_not_run(tmp_path: Path) -> None:
    sentinel = tmp_path / "pwned"
    pickled = pickle.dumps(_RunsShell(f"touch {sentinel}"), protocol=2)
    path = _write_pt(tmp_path / "evil.pt", pickled, {})
    with pytest.raises(UnsupportedPickleError) as info:
        load_state_dict(path)
    system = f"{os.system.__module__}.system"  # posix.system on Linux
    assert info.value.global_name == system
    assert str(path) in str(info.value) and system in str(info.value)
    assert not sentinel.exists()
    assert issubclass(UnsupportedPickleError, ValueError)


@pytest.mark.parametrize(
    "module, name",
    [("builtins", "exec"), ("numpy.core.multiarray", "_reconstruct"), ("torch", "load")],
)
def test_other_globals_are_refused(tmp_path: Path, module: str, name: str) -> None:
    pickled = _state_dict({"w": _call(_global(module, name), _str("x"))})
    with pytest.raises(UnsupportedPickleError, match=rf"'{module}\.{name}'"):
        load_state_dict(_write_pt(tmp_path / "g.pt", pickled, {}))


def test_not_a_zip(tmp_path: Path) -> None:
    path = tmp_path / "plain.pt"
    path.write_bytes(b"this is not a zip archive")
    with pytest.raises(StateDictError, match="not a zip archive") as info:
        load_state_dict(path)
    assert str(path) in str(info.value)


def test_missing_file(tmp_path: Path) -> None:
    path = tmp_path / "absent.pt"
    with pytest.raises(StateDictError, match="cannot open") as info:
        load_state_dict(path)
    assert str(path) in str(info.value)


def test_no_data_pkl(tmp_path: Path) -> None:
    path = tmp_path / "empty.pt"
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("archive/version", "3\n")
    with pytest.raises(StateDictError, match="data.pkl") as info:
        load_state_dict(path)
    assert str(path) in str(info.value)


def test_missing_storage_record(tmp_path: Path) -> None:
    pickled = _state_dict({"w": _tensor(_storage("FloatStorage", "7", 2), 0, (2,), (1,))})
    path = _write_pt(tmp_path / "m.pt", pickled, {})
    with pytest.raises(StateDictError, match=r"'archive/data/7' \(storage key '7'\) is missing"):
        load_state_dict(path)


def test_strides_beyond_storage(tmp_path: Path) -> None:
    pickled = _state_dict({"w": _tensor(_storage("FloatStorage", "0", 4), 1, (2, 2), (2, 1))})
    path = _write_pt(tmp_path / "oob.pt", pickled, {"0": np.zeros(4, np.float32).tobytes()})
    with pytest.raises(StateDictError, match=r"tensor 'w'.*reach element 4 of a storage of 4"):
        load_state_dict(path)
