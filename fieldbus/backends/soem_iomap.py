"""SOEM's IO map as one writable view, so the cycle moves process data without a ``bytes`` per slave.

pysoem (1.1.13) shows each slave's part of the IO map only as ``bytes``
(``slave.output`` / ``slave.input``: a new object per access, and a setter that
takes ``bytes`` only). Its ``Master`` keeps the IO map inside its own object
(``cdef char io_map[EC_IOMAPSIZE]``, pysoem.pyx), which in CPython lives at a
fixed place for the master's life. :func:`locate` finds it there once, at
SAFE-OP, with a pattern written through pysoem's own setter, and proves the
layout through pysoem's own getters: every slave's outputs and inputs must
read back as the expected slice of the view (outputs of all slaves in bus
order, then inputs: SOEM's ``ecx_config_map_group`` without overlap). Anything
else - another interpreter, a pysoem that keeps the map elsewhere, bit-packed
slaves sharing a byte - and :func:`locate` returns None: the caller keeps the
per-slave ``bytes`` path.

The view must not outlive the master (the backend drops it at ``close()``).
"""

from __future__ import annotations

import ctypes
import os
import sys
from collections.abc import Sequence
from typing import Any

import numpy as np
import numpy.typing as npt


def locate(
    master: Any, slaves: Sequence[Any], sizes: Sequence[tuple[int, int]]
) -> npt.NDArray[np.uint8] | None:
    """SOEM's IO map of ``master`` as a uint8 array (outputs, then inputs), or None when not proven.

    ``sizes``: each slave's (output, input) bytes as SOEM mapped them. Call at
    SAFE-OP (outputs are overwritten with zeros; nothing is sent meanwhile).
    """
    if sys.implementation.name != "cpython" or len(slaves) != len(sizes):
        return None
    out_total = sum(o for o, _ in sizes)
    in_total = sum(i for _, i in sizes)
    if not out_total:
        return None  # the pattern is written through output setters
    pattern = os.urandom(out_total)
    at = 0
    for s, (o, _) in zip(slaves, sizes, strict=True):
        if o:
            s.output = pattern[at : at + o]
            at += o
    base, size = id(master), type(master).__basicsize__
    memory = ctypes.string_at(base, size)
    found = memory.find(pattern)
    if found < 0 or memory.find(pattern, found + 1) >= 0 or found + out_total + in_total > size:
        _clear(slaves, sizes)
        return None
    buffer = (ctypes.c_uint8 * (out_total + in_total)).from_address(base + found)
    view: npt.NDArray[np.uint8] = np.ctypeslib.as_array(buffer)
    view[out_total:] = np.frombuffer(os.urandom(in_total), dtype=np.uint8)
    ok = _matches(view, slaves, sizes, out_total)
    view[:] = 0
    if not ok:
        _clear(slaves, sizes)
        return None
    return view


def _matches(
    view: npt.NDArray[np.uint8], slaves: Sequence[Any], sizes: Sequence[tuple[int, int]], out_total: int
) -> bool:
    """Every slave's ``output`` and ``input`` (pysoem's getters) equal their slices of ``view``."""
    o_at, i_at = 0, out_total
    for s, (o, i) in zip(slaves, sizes, strict=True):
        if o and bytes(s.output) != view[o_at : o_at + o].tobytes():
            return False
        if i and bytes(s.input) != view[i_at : i_at + i].tobytes():
            return False
        o_at += o
        i_at += i
    return True


def _clear(slaves: Sequence[Any], sizes: Sequence[tuple[int, int]]) -> None:
    for s, (o, _) in zip(slaves, sizes, strict=True):
        if o:
            s.output = bytes(o)
