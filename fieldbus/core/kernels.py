"""Small-array steps of the cycle as one call each: the C kernels of :mod:`fieldbus._codec` where it is
built, numpy otherwise (the same results; tests/unit/test_kernels.py runs both).

On the dozen-row arrays of a cycle a numpy call costs about a microsecond whatever it computes, so a
clean cycle's test that takes three ufuncs takes three microseconds; the kernel takes one call. Each
factory binds its arrays once, at bring-up, and returns what the cycle calls. The arrays must outlive
the returned callable and keep their shape (the C kernels hold their buffers).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import numpy.typing as npt

try:
    from fieldbus import _codec  # type: ignore[attr-defined]
except ImportError:  # not built: numpy below
    _codec = None

#: the C kernels are used (False: numpy; tests switch it to compare both)
native = _codec is not None and hasattr(_codec, "Window")


def window(
    values: npt.NDArray[np.floating[Any]],
    last: npt.NDArray[np.floating[Any]],
    lo: npt.NDArray[np.floating[Any]] | None = None,
    hi: npt.NDArray[np.floating[Any]] | None = None,
) -> Callable[[], bool]:
    """``() -> bool``: every value lies in ``[lo, hi]`` (without a window: is finite; NaN lies in none);
    then ``values`` are copied into ``last`` and True is returned, else ``last`` is left as it was.
    Arrays of one shape and float dtype (1-D or 2-D, any strides; ``last`` writable; C for float64)."""
    if (lo is None) != (hi is None):
        raise ValueError("lo and hi: both or neither")
    if (
        native
        and values.ndim <= 2
        and all(a is None or a.dtype == np.float64 for a in (values, last, lo, hi))
    ):
        check: Callable[[], bool] = _codec.Window(values, last, lo, hi).clean
        return check
    ok = np.zeros(values.shape, dtype=bool)
    if lo is None or hi is None:
        size = values.size

        def finite() -> bool:
            np.isfinite(values, out=ok)
            if np.count_nonzero(ok) != size:
                return False
            np.copyto(last, values)
            return True

        return finite
    work = np.zeros(values.shape, dtype=values.dtype)

    def inside() -> bool:
        np.minimum(values, hi, out=work)
        np.maximum(work, lo, out=work)
        np.not_equal(work, values, out=ok)  # NaN != NaN: outside
        if np.count_nonzero(ok):
            return False
        np.copyto(last, values)
        return True

    return inside


def any_bits(words: npt.NDArray[np.integer[Any]], mask: int) -> Callable[[], bool]:
    """``() -> bool``: a word of ``words`` (integers, 1-D or 2-D, any strides; C for 16-bit words) has a
    bit of ``mask`` set."""
    if native and words.dtype.kind in "iu" and words.dtype.itemsize == 2 and words.ndim <= 2:
        test: Callable[[], bool] = _codec.AnyBits(words, mask).any
        return test
    bits = np.zeros(words.shape, dtype=words.dtype)
    m = words.dtype.type(mask)

    def any_set() -> bool:
        np.bitwise_and(words, m, out=bits)
        return bool(np.count_nonzero(bits))

    return any_set


def copier(dst: npt.NDArray[np.uint8], src: npt.NDArray[np.uint8]) -> Callable[[], Any]:
    """``() -> None``: ``src``'s bytes into ``dst`` (uint8 arrays of one shape, 1-D or 2-D, any strides)."""
    if dst.shape != src.shape:
        raise ValueError(f"copy of shape {src.shape} into {dst.shape}")
    if native and dst.dtype == src.dtype == np.uint8 and dst.ndim <= 2:
        run: Callable[[], Any] = _codec.Copy(dst, src).run
        return run

    def copy() -> None:
        np.copyto(dst, src)

    return copy
