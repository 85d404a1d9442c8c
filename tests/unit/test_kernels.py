"""The cycle's small-array kernels (fieldbus.core.kernels): the C kernels and the numpy path agree.

Differential: the same arrays (strided views into wider rows, as the process image lays them out)
go through both paths, and the answers and every byte written must be identical; the numpy path is
also checked against the rule written out element by element (a scalar oracle). Values are drawn
where a comparison can go wrong: NaN, +-inf, -0.0, the window's edges and one step past them, the
largest finite float64.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fieldbus.core import kernels

EDGES = [0.0, -0.0, 1.0, -1.0, 2.5, -2.5, math.inf, -math.inf, math.nan, 1.7976931348623157e308, -1e-300]

needs_c = pytest.mark.skipif(not kernels.native, reason="fieldbus._codec is not built (numpy path only)")


def _paths(monkeypatch: pytest.MonkeyPatch, build: Callable[[], Any]) -> tuple[Any, Any]:
    """``build()`` once with the C kernels and once with numpy (each on fresh arrays it makes)."""
    monkeypatch.setattr(kernels, "native", True)
    c = build()
    monkeypatch.setattr(kernels, "native", False)
    py = build()
    return c, py


def _rows(values: list[float], n: int, m: int) -> np.ndarray:
    """(n, m) float64 columns 1..m of rows of m + 2 floats: a strided view, as the image's scaled block."""
    wide = np.zeros((n, m + 2))
    wide[:, 1 : m + 1] = np.array(values, dtype=np.float64).reshape(n, m)
    return wide[:, 1 : m + 1]


@needs_c
@settings(max_examples=300, deadline=None)
@given(
    data=st.data(),
    n=st.integers(1, 6),
    m=st.integers(1, 3),
    windowed=st.booleans(),
)
def test_window_c_and_numpy_agree_with_the_rule(data: st.DataObject, n: int, m: int, windowed: bool) -> None:
    values = data.draw(st.lists(st.sampled_from(EDGES) | st.floats(-3, 3), min_size=n * m, max_size=n * m))
    lo = np.array(
        data.draw(st.lists(st.sampled_from([-2.5, -1.0, 0.0, -0.0]), min_size=n * m, max_size=n * m))
    )
    hi = np.array(data.draw(st.lists(st.sampled_from([2.5, 1.0, 0.0, -0.0]), min_size=n * m, max_size=n * m)))
    lo, hi = lo.reshape(n, m), hi.reshape(n, m)
    answers, lasts = [], []
    with pytest.MonkeyPatch.context() as mp:
        for native in (True, False):
            mp.setattr(kernels, "native", native)
            x = _rows(values, n, m)
            last = np.full((n, m), 7.0)
            check = kernels.window(x, last, lo, hi) if windowed else kernels.window(x, last)
            answers.append(check())
            lasts.append(last.copy())
    flat = np.array(values).reshape(n, m)
    rule = all(
        (lo[i, j] <= flat[i, j] <= hi[i, j]) if windowed else math.isfinite(flat[i, j])
        for i in range(n)
        for j in range(m)
    )
    assert answers == [rule, rule]
    expected = flat if rule else np.full((n, m), 7.0)  # copied when clean, untouched otherwise
    for last in lasts:
        assert last.tobytes() == expected.tobytes()  # bit for bit: -0.0 stays -0.0


def test_window_numpy_path_refuses_nan_and_infinity(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(kernels, "native", False)
    x = _rows([0.0] * 6, 3, 2)
    last = np.zeros((3, 2))
    check = kernels.window(x, last)
    assert check()
    for bad in (math.nan, math.inf, -math.inf):
        x[1, 1] = bad
        last[:] = 5.0
        assert not check()
        assert (last == 5.0).all()
    x[1, 1] = 1.25
    assert check() and last[1, 1] == 1.25


def test_window_float32_block_takes_the_numpy_path(monkeypatch: pytest.MonkeyPatch) -> None:
    """A raw-CAN float32 field: not the C kernel's dtype, the same answers through numpy."""
    x = np.zeros((4, 1), dtype=np.float32)
    last = np.zeros((4, 1), dtype=np.float32)
    lo, hi = np.full((4, 1), -1, np.float32), np.full((4, 1), 1, np.float32)
    check = kernels.window(x, last, lo, hi)
    x[2, 0] = 0.5
    assert check() and last[2, 0] == np.float32(0.5)
    x[2, 0] = 1.5
    assert not check() and last[2, 0] == np.float32(0.5)


def test_window_lo_and_hi_both_or_neither() -> None:
    x = np.zeros((2, 2))
    with pytest.raises(ValueError):
        kernels.window(x, x.copy(), np.zeros((2, 2)), None)


@needs_c
def test_window_c_kernel_refuses_a_shape_mismatch(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(kernels, "native", True)
    with pytest.raises(ValueError, match="shapes"):
        kernels.window(np.zeros((3, 2)), np.zeros((2, 3)))


@needs_c
@settings(max_examples=200, deadline=None)
@given(words=st.lists(st.integers(0, 0xFFFF), min_size=1, max_size=16), mask=st.integers(0, 0xFFFF))
def test_any_bits_c_and_numpy_agree(words: list[int], mask: int) -> None:
    rows = np.zeros(len(words), dtype=[("pad", "u1"), ("sw", "<u2"), ("more", "u1")])  # a strided field
    rows["sw"] = words
    got = []
    with pytest.MonkeyPatch.context() as mp:
        for native in (True, False):
            mp.setattr(kernels, "native", native)
            got.append(kernels.any_bits(rows["sw"], mask)())
    assert got == [any(w & mask for w in words)] * 2


def test_any_bits_follows_the_words(monkeypatch: pytest.MonkeyPatch) -> None:
    for native in (False, True) if kernels.native else (False,):
        monkeypatch.setattr(kernels, "native", native)
        sw = np.zeros(12, dtype=np.uint16)
        fault = kernels.any_bits(sw, 0x0008)
        assert not fault()
        sw[7] = 0x0237 | 0x0008
        assert fault()
        sw[7] = 0x0237
        assert not fault()


@needs_c
@settings(max_examples=100, deadline=None)
@given(n=st.integers(0, 8), w=st.integers(0, 9), pad=st.integers(0, 9), seed=st.integers(0, 2**32 - 1))
def test_copier_c_and_numpy_agree(n: int, w: int, pad: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    src_rows = rng.integers(0, 256, (n, w + pad), dtype=np.uint8)
    out = []
    with pytest.MonkeyPatch.context() as mp:
        for native in (True, False):
            mp.setattr(kernels, "native", native)
            dst_rows = np.full((n, w + 3), 0xAA, np.uint8)
            kernels.copier(dst_rows[:, 1 : w + 1], src_rows[:, :w])()
            out.append(dst_rows.tobytes())
    expected = np.full((n, w + 3), 0xAA, np.uint8)
    expected[:, 1 : w + 1] = src_rows[:, :w]
    assert out == [expected.tobytes()] * 2  # the bytes beside the view untouched


def test_copier_refuses_a_shape_mismatch() -> None:
    with pytest.raises(ValueError, match="shape"):
        kernels.copier(np.zeros((2, 3), np.uint8), np.zeros((3, 2), np.uint8))


@needs_c
def test_the_cycle_uses_the_c_kernels_when_built() -> None:
    """The bring-up binds the C kernels (a Window's ``clean``), not the numpy closures."""
    x = np.zeros((2, 2))
    assert type(kernels.window(x, x.copy())).__name__ == "builtin_function_or_method"
    assert type(kernels.copier(np.zeros(3, np.uint8), np.zeros(3, np.uint8))).__name__ == (
        "builtin_function_or_method"
    )
