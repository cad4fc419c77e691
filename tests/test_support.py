"""The test support itself: field-by-field comparison and the compile counter can fail."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import struct
from support.asserts import assert_tree_close, assert_tree_equal, leaves
from support.compiles import compile_counter


class _Result(NamedTuple):
    x: np.ndarray
    flag: np.ndarray


@struct.dataclass
class _Record:
    a: np.ndarray
    b: dict
    c: np.ndarray | None = None
    label: str = struct.field(pytree_node=False, default="r")


def _record(**kw):
    base = dict(a=np.arange(6.0).reshape(2, 3),
                b={"u": _Result(np.ones(4), np.zeros(4, bool)), "v": [1.0, 2.0]})
    return _Record(**(base | kw))


def test_equal_records_pass_and_a_failure_names_the_field_and_the_difference():
    assert_tree_equal(_record(), _record())
    other = _record(b={"u": _Result(np.array([1.0, 1.0, 1.5, 1.0]), np.zeros(4, bool)),
                       "v": [1.0, 2.0]})
    with pytest.raises(AssertionError) as e:
        assert_tree_close(other, _record(), rtol=1e-3, what="ours vs ref")
    msg = str(e.value)
    assert msg.startswith("ours vs ref: 1 field(s) differ")
    assert ".b['u'].x: 1 of 4 elements" in msg and "max |a-b| = 0.5 at (2,)" in msg
    assert "max |a-b|/|b| = 0.5" in msg


def test_every_failing_field_is_listed_and_structure_is_named_by_path():
    bad = _record(a=np.zeros((2, 3)), c=np.ones(2), label="s")
    with pytest.raises(AssertionError) as e:
        assert_tree_equal(bad, _record())
    msg = str(e.value)
    assert ".c: array vs None" in msg
    bad = _record(a=np.zeros((2, 3)), label="s")
    with pytest.raises(AssertionError) as e:
        assert_tree_equal(bad, _record())
    assert ".a: 5 of 6 elements" in str(e.value) and ".label: 's' != 'r'" in str(e.value)
    assert_tree_equal(bad.replace(a=_record().a), _record(), static=False)
    with pytest.raises(AssertionError, match=r"\['w'\]: absent vs array"):
        assert_tree_equal({"v": 1.0}, {"v": 1.0, "w": 2.0})
    with pytest.raises(AssertionError, match=r"<root>: shape \(3,\) != \(1, 3\)"):
        assert_tree_close(np.zeros(3), np.zeros((1, 3)))
    with pytest.raises(AssertionError, match="dtype float32 != float64"):
        assert_tree_equal(np.zeros(3, np.float32), np.zeros(3))


def test_mappings_pair_by_key_and_lists_of_numbers_are_arrays():
    ours = {"b": np.ones(2), "a": np.zeros(3)}  # another insertion order than the reference
    assert_tree_equal(ours, {"a": np.zeros(3), "b": np.ones(2)})
    assert [p for p, _ in leaves(ours)] == ["['a']", "['b']"]
    assert_tree_close({"w": np.array([0.25, 0.75])}, {"w": [0.25, 0.75]})  # JSON vs computed


def test_tolerances_are_those_of_numpy_assert_allclose():
    desired = np.array([1.0, 100.0])
    for actual in (desired + [1e-6, 1e-4], desired + [2e-6, 0.0], desired + [0.0, 2.1e-4]):
        try:
            np.testing.assert_allclose(actual, desired, rtol=1e-6, atol=1e-6)
            numpy_ok = True
        except AssertionError:
            numpy_ok = False
        try:
            assert_tree_close(actual, desired, rtol=1e-6, atol=1e-6)
            ours_ok = True
        except AssertionError:
            ours_ok = False
        assert ours_ok == numpy_ok, actual
    nan = np.array([np.nan, 1.0])
    assert_tree_close(nan, nan.copy())
    with pytest.raises(AssertionError):
        assert_tree_close(nan, nan.copy(), equal_nan=False)


def test_compile_counter_counts_new_shapes_only():
    @jax.jit
    def _counted_twice(x):
        return jnp.sin(x) * 2.0

    with compile_counter("_counted_twice") as seen:
        _counted_twice(jnp.ones(3))
        _counted_twice(jnp.zeros(3))  # same shape: served from the cache
    assert seen.traces["_counted_twice"] == 1 and seen.compiles["_counted_twice"] == 1
    with compile_counter("_counted_twice") as seen:
        _counted_twice(jnp.ones(5))
        _counted_twice(jnp.ones(3))
    assert seen.traces["_counted_twice"] == 1 and seen.compiles["_counted_twice"] == 1
    with compile_counter("another_name") as seen:
        _counted_twice(jnp.ones(7))
    assert not seen.compiles and not seen.traces
