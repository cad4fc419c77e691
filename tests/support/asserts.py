"""Field-by-field comparison of structured results: a failure names the field that failed.

As MJX's tests compare ``mjx.Data`` with MuJoCo's ``MjData`` one attribute at a time
(``_assert_attr_eq``), :func:`assert_tree_close` walks two nested records side by side
(dicts, dataclasses such as flax structs, NamedTuples, lists and tuples; a list of numbers
is one array leaf, so a JSON table compares with a computed one) and checks every
leaf; the error lists each failing field by its path (``.T.x``, ``['params']['out']``)
with its largest absolute and relative difference.

Array leaves are compared as ``np.testing.assert_allclose`` does,
``|actual - desired| <= atol + rtol * |desired|`` element by element, with equal shapes
(no broadcasting). ``None`` matches only ``None``; other leaves (strings, static fields
such as module definitions) must be equal.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

import numpy as np

__all__ = ["assert_tree_close", "assert_tree_equal", "difference", "leaves"]


_SCALARS = (bool, int, float, complex, np.generic)


def _is_array(x) -> bool:
    return hasattr(x, "shape") and hasattr(x, "dtype")


def _is_flat(seq) -> bool:
    """A list or tuple compared as one leaf: all strings, or all numbers (as JSON gives)."""
    return all(isinstance(v, str) for v in seq) or all(isinstance(v, _SCALARS) for v in seq)


def _is_numeric(x) -> bool:
    if isinstance(x, (list, tuple)):
        return len(x) > 0 and all(isinstance(v, _SCALARS) for v in x)
    return isinstance(x, _SCALARS) or _is_array(x)


def leaves(tree, path: str = "", *, static: bool = True) -> list[tuple[str, object]]:
    """``(path, leaf)`` of every leaf of a nested record, in its own order.

    ``static=False`` leaves out the fields of flax structs marked ``pytree_node=False``.
    """
    if isinstance(tree, Mapping):  # in key order, so two mappings pair up leaf by leaf
        out = []
        for k in sorted(tree, key=repr):
            out += leaves(tree[k], f"{path}[{k!r}]", static=static)
        return out
    if dataclasses.is_dataclass(tree) and not isinstance(tree, type):
        out = []
        for f in dataclasses.fields(tree):
            if static or f.metadata.get("pytree_node", True):
                out += leaves(getattr(tree, f.name), f"{path}.{f.name}", static=static)
        return out
    if isinstance(tree, tuple) and hasattr(tree, "_fields"):  # NamedTuple
        out = []
        for name in tree._fields:
            out += leaves(getattr(tree, name), f"{path}.{name}", static=static)
        return out
    if isinstance(tree, (list, tuple)) and not _is_flat(tree):
        out = []
        for i, v in enumerate(tree):
            out += leaves(v, f"{path}[{i}]", static=static)
        return out
    return [(path, tree)]


def _structure(tree, path: str, static: bool) -> dict[str, str]:
    """Path -> a short kind of every node, to report structural differences by path."""
    kinds = {}
    if isinstance(tree, Mapping):
        kinds[path] = "mapping with keys " + ", ".join(sorted(map(repr, tree)))
        for k, v in tree.items():
            kinds.update(_structure(v, f"{path}[{k!r}]", static))
    elif dataclasses.is_dataclass(tree) and not isinstance(tree, type):
        kinds[path] = type(tree).__name__
        for f in dataclasses.fields(tree):
            if static or f.metadata.get("pytree_node", True):
                kinds.update(_structure(getattr(tree, f.name), f"{path}.{f.name}", static))
    elif isinstance(tree, tuple) and hasattr(tree, "_fields"):
        kinds[path] = type(tree).__name__
        for name in tree._fields:
            kinds.update(_structure(getattr(tree, name), f"{path}.{name}", static))
    elif isinstance(tree, (list, tuple)) and not _is_flat(tree):
        kinds[path] = f"{type(tree).__name__} of length {len(tree)}"
        for i, v in enumerate(tree):
            kinds.update(_structure(v, f"{path}[{i}]", static))
    elif tree is None:
        kinds[path] = "None"
    elif _is_numeric(tree):
        kinds[path] = "array"
    else:
        kinds[path] = "value"
    return kinds


def difference(actual, desired, *, equal_nan: bool = True) -> str:
    """The largest absolute and relative difference of two arrays, and where."""
    a, b = np.asarray(actual), np.asarray(desired)
    if a.shape != b.shape:
        return f"shapes {a.shape} vs {b.shape}"
    if a.size == 0:
        return "empty"
    if a.dtype.kind not in "biufc" or b.dtype.kind not in "biufc":
        return f"{int(np.sum(a != b))} of {a.size} elements differ"
    a = a.astype(np.complex128 if "c" in a.dtype.kind + b.dtype.kind else np.float64)
    b = b.astype(a.dtype)
    with np.errstate(invalid="ignore", divide="ignore"):
        err = np.abs(a - b)
        same = (a == b) | (equal_nan & np.isnan(a) & np.isnan(b))
        err = np.where(same, 0.0, np.where(np.isnan(err), np.inf, err))
        rel = np.where(err == 0, 0.0, err / np.abs(b))
        rel = np.where(np.isnan(rel), np.inf, rel)
    i = np.unravel_index(np.argmax(err), err.shape)
    where = f" at {tuple(int(k) for k in i)}" if a.ndim else ""
    return (f"max |a-b| = {err[i]:.3g}{where} ({a[i].item()!r} vs {b[i].item()!r}), "
            f"max |a-b|/|b| = {np.max(rel):.3g}")


def _leaf_failure(a, b, rtol, atol, equal_nan, dtype) -> str | None:
    if a is None or b is None:
        return None if a is None and b is None else f"{a!r} vs {b!r}"
    if not (_is_numeric(a) and _is_numeric(b)):
        return None if a == b else f"{a!r} != {b!r}"
    x, y = np.asarray(a), np.asarray(b)
    if x.shape != y.shape:
        return f"shape {x.shape} != {y.shape}"
    if dtype and x.dtype != y.dtype:
        return f"dtype {x.dtype} != {y.dtype}"
    if x.dtype.kind not in "biufc" or y.dtype.kind not in "biufc":
        return None if np.array_equal(x, y) else difference(x, y)
    if x.dtype == bool or y.dtype == bool:
        x, y = x.astype(np.int64), y.astype(np.int64)
    ok = np.isclose(x, y, rtol=rtol, atol=atol, equal_nan=equal_nan)
    if np.all(ok):
        return None
    return (f"{int(np.sum(~ok))} of {x.size} elements beyond atol={atol:g}, rtol={rtol:g}; "
            + difference(x, y, equal_nan=equal_nan))


def assert_tree_close(actual, desired, *, rtol: float = 1e-7, atol: float = 0.0,
                      equal_nan: bool = True, dtype: bool = False, static: bool = True,
                      what: str = "") -> None:
    """Asserts two nested records have the same fields and close leaves, field by field.

    Args:
      rtol, atol: as ``np.testing.assert_allclose`` (same defaults).
      equal_nan: NaN in both at the same place counts as equal.
      dtype: also require equal dtypes of array leaves.
      static: also compare flax structs' static (``pytree_node=False``) fields.
      what: prefix of the error message (what is compared with what).
    """
    sa, sb = _structure(actual, "", static), _structure(desired, "", static)
    problems = [f"{p or '<root>'}: {sa.get(p, 'absent')} vs {sb.get(p, 'absent')}"
                for p in sorted(set(sa) | set(sb)) if sa.get(p) != sb.get(p)]
    if not problems:
        for (path, a), (_, b) in zip(leaves(actual, static=static),
                                     leaves(desired, static=static)):
            failure = _leaf_failure(a, b, rtol, atol, equal_nan, dtype)
            if failure is not None:
                problems.append(f"{path or '<root>'}: {failure}")
    if problems:
        head = f"{what}: " if what else ""
        raise AssertionError(head + f"{len(problems)} field(s) differ:\n  "
                             + "\n  ".join(problems))


def assert_tree_equal(actual, desired, *, dtype: bool = True, equal_nan: bool = True,
                      static: bool = True, what: str = "") -> None:
    """:func:`assert_tree_close` with no tolerance and, by default, equal dtypes."""
    assert_tree_close(actual, desired, rtol=0.0, atol=0.0, equal_nan=equal_nan, dtype=dtype,
                      static=static, what=what)
