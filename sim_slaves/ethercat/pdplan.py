"""Precomputed process-data paths of an :class:`~sim_slaves.ethercat.chain.EscChain`.

:class:`CopyPlan`: what one LRD/LWR/LRW datagram (command, logical address,
length, place in the frame) does to the chain, worked out once from every
slave's FMMUs and kept until an FMMU, a SyncManager or an AL state changes:
index arrays of the frame bytes copied into slave memory and of the memory
bytes copied into the frame (two numpy copies per datagram, whatever the
number of slaves), the working-counter increment and which slaves it touched.
A plan does not depend on whether its slaves are in SAFE-OP or OP: outside OP
an ESC's output SyncManager takes no writes, and the chain takes those slaves'
writes off the working counter per datagram (``writers``).
A datagram whose copies interact (a slave reading bytes an earlier slave
wrote in the same datagram, as in SOEM's overlapping LRW) keeps the exact
order of the slaves: its plan is a list of slice copies in wire order.

:class:`DriveLink`: the CiA 402 objects of every fast slave's process data
as index arrays into the chain's memory, so the drives of a
:class:`~sim_slaves.drive_bank.DriveBank` read their targets from, and write
their actual values to, ESC memory in a few numpy operations per cycle.
Memory is the chain's one array of ``slaves x MEM_SIZE`` bytes.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
import numpy.typing as npt

from fieldbus.core.pdo.layout import DirectionLayout
from sim_slaves.drive_bank import DriveBank, runs
from sim_slaves.ethercat.al import AlState
from sim_slaves.ethercat.esc import MEM_SIZE, Esc

Index = npt.NDArray[np.intp]
#: a drive group as ``sim_slaves._pdlink`` takes it after the memory: addresses, slots, kinds, bank arrays
CArgs = tuple[npt.NDArray[np.int64], npt.NDArray[np.int64], bytes, tuple[npt.NDArray[np.int64], ...]]


class _PdLink(Protocol):
    """``sim_slaves._pdlink`` (``sim_slaves/_pdlink.c``)."""

    gather: Callable[..., None]
    scatter: Callable[..., None]


def _c_link() -> _PdLink | None:
    try:
        from sim_slaves import _pdlink
    except ImportError:
        return None
    return _pdlink


#: the drive link's gather/scatter in C for the chain's lean path, or None where not built (then numpy)
pdlink = _c_link()
_LRD, _LWR = 10, 11


@dataclass
class CopyPlan:
    """One logical datagram's effect: copies, WKC increment, slaves touched."""

    write_frame: Index  # frame byte -> memory byte (outputs)
    write_mem: Index
    read_frame: Index  # memory byte -> frame byte (inputs)
    read_mem: Index
    wkc: int  # with every slave's outputs taken (all in OP); see ``writers``
    writers: Index  # wire indices of the slaves whose outputs it writes (each counts ``write_inc``)
    write_inc: int  # a write's share of the working counter: LRW 2, LWR 1
    fast_written: Index  # wire indices of fast slaves whose outputs were written
    fast_touched: Index  # bank slots of fast drives that got outputs (or have none and exchanged inputs)
    fast_read: Index  # bank slots of fast drives whose inputs the datagram reads
    slow: list[tuple[Esc, bool]]  # (slave, outputs written) handled by Esc.cycle
    ordered: list[tuple[bool, int, int, int]] | None = None  # (write?, frame, memory, length) in wire order
    spans: list[tuple[bool, int, int, int]] = field(default_factory=list)  # every copy, in wire order
    written_runs: list[tuple[int, int]] = field(default_factory=list)  # ``fast_written`` as runs
    touched_runs: list[tuple[int, int]] = field(default_factory=list)  # ``fast_touched`` as runs

    def apply_spans(self, frame: memoryview, memory: memoryview) -> None:
        """:meth:`apply` as slice copies in wire order (``frame``, ``memory``: byte views): the same bytes
        move (copies of a plan that does not keep the order touch disjoint bytes), in fewer calls for the
        few copies of a chain's cycle."""
        for write, fo, mo, n in self.spans:
            if write:
                memory[mo : mo + n] = frame[fo : fo + n]
            else:
                frame[fo : fo + n] = memory[mo : mo + n]

    def apply(self, frame: npt.NDArray[np.uint8], memory: npt.NDArray[np.uint8]) -> None:
        """Do the copies between ``frame`` (the whole frame buffer) and the chain's memory."""
        if self.ordered is not None:
            for write, fo, mo, n in self.ordered:
                if write:
                    memory[mo : mo + n] = frame[fo : fo + n]
                else:
                    frame[fo : fo + n] = memory[mo : mo + n]
            return
        if len(self.write_frame):
            memory[self.write_mem] = frame[self.write_frame]
        if len(self.read_frame):
            frame[self.read_frame] = memory[self.read_mem]


def build_copy_plan(
    slaves: Sequence[Esc],
    fast: Sequence[bool],
    slots: Sequence[int],
    cmd: int,
    laddr: int,
    length: int,
    doff: int,
) -> CopyPlan:
    """Walk the slaves once (as ``Esc.logical`` would) and record what the datagram copies.

    ``fast[i]``: slave i's cycle is the chain's (no ``Esc.cycle``); ``slots[i]``:
    its drive's bank slot or -1.
    """
    ops: list[tuple[bool, int, int, int]] = []
    wkc = 0
    written: list[int] = []
    touched: list[int] = []
    read: list[int] = []
    writers: list[int] = []
    slow: list[tuple[Esc, bool]] = []
    lend = laddr + length
    for i, s in enumerate(slaves):
        if not s.pd_active:
            continue
        inc = 0
        for ls, le, ps, wr in s.lmap:
            if ls >= lend or le <= laddr:
                continue
            lo, hi = max(ls, laddr), min(le, lend)
            fo, mo = doff + lo - laddr, i * MEM_SIZE + ps + lo - ls
            if wr:
                if cmd != _LRD:
                    ops.append((True, fo, mo, hi - lo))
                    inc |= 2
            elif cmd != _LWR:
                ops.append((False, fo, mo, hi - lo))
                inc |= 1
        if not inc:
            continue
        wkc += 1 if cmd == _LWR else inc
        if inc & 2:
            writers.append(i)
        if fast[i]:
            if inc & 2:
                written.append(i)
            if slots[i] >= 0:
                if inc & 2 or not s.image.outputs.size:
                    touched.append(slots[i])
                if inc & 1:
                    read.append(slots[i])
        else:
            slow.append((s, bool(inc & 2)))
    w = [op for op in ops if op[0]]
    r = [op for op in ops if not op[0]]
    wf, wm = _ranges(w)
    rf, rm = _ranges(r)
    # copies that share frame or memory bytes must keep the slaves' order
    interacting = _overlaps([(fo, n) for _, fo, _, n in ops]) or _overlaps([(mo, n) for _, _, mo, n in ops])
    return CopyPlan(
        write_frame=wf,
        write_mem=wm,
        read_frame=rf,
        read_mem=rm,
        wkc=wkc,
        writers=np.array(writers, dtype=np.intp),
        write_inc=1 if cmd == _LWR else 2,
        fast_written=np.array(written, dtype=np.intp),
        fast_touched=np.array(touched, dtype=np.intp),
        fast_read=np.array(read, dtype=np.intp),
        slow=slow,
        ordered=ops if interacting else None,
        spans=ops,
        written_runs=runs(np.array(written, dtype=np.intp)),
        touched_runs=runs(np.array(sorted(set(touched)), dtype=np.intp)),
    )


def _overlaps(spans: list[tuple[int, int]]) -> bool:
    """True when two of the (start, length) byte spans share a byte."""
    end = -1
    for start, n in sorted(spans):
        if start < end:
            return True
        end = max(end, start + n)
    return False


def _ranges(ops: list[tuple[bool, int, int, int]]) -> tuple[Index, Index]:
    if not ops:
        empty = np.zeros(0, dtype=np.intp)
        return empty, empty
    frame = np.concatenate([np.arange(fo, fo + n, dtype=np.intp) for _, fo, _, n in ops])
    mem = np.concatenate([np.arange(mo, mo + n, dtype=np.intp) for _, _, mo, n in ops])
    return frame, mem


# CiA 402 objects the bank exchanges: (index, bank array, numpy type of the PDO entry)
DRIVE_INPUTS = (
    (0x6040, "controlword", "<u2"),
    (0x6060, "mode_request", "i1"),
    (0x607A, "target_position", "<i4"),
    (0x60FF, "target_velocity", "<i4"),
    (0x6071, "target_torque", "<i2"),
)
DRIVE_OUTPUTS = (
    (0x6041, "statusword", "<u2"),
    (0x6061, "mode_display", "i1"),
    (0x6064, "position_counts", "<i4"),
    (0x606C, "velocity_counts", "<i4"),
    (0x6077, "torque_permille", "<i2"),
    (0x60F4, "following_error", "<i4"),
    (0x603F, "error_code", "<u2"),
)
_TYPE = {("uint", 16): "<u2", ("int", 8): "i1", ("int", 32): "<i4", ("int", 16): "<i2", ("uint", 8): "u1"}


def pdo_offsets(lay: DirectionLayout) -> dict[int, tuple[int, str]] | None:
    """Sub-index-0 objects of a direction: index -> (byte offset, numpy type); None if one is not byte aligned."""
    out: dict[int, tuple[int, str]] = {}
    for e in lay.entries:
        ch = e.channel
        if ch.is_gap or ch.sub_index != 0:
            continue
        kind = _TYPE.get((ch.type.kind, ch.bits))
        if e.bit_offset % 8 or kind is None:
            if ch.index in _DRIVE_OBJECTS:
                return None
            continue
        out[ch.index] = (e.bit_offset // 8, kind)
    return out


_DRIVE_OBJECTS = frozenset(index for index, _, _ in (*DRIVE_INPUTS, *DRIVE_OUTPUTS))


@dataclass
class _Group:
    """Drives whose process data carry the same CiA 402 objects: one fancy copy for all of them.

    ``index``: (drives, bytes) memory indices of the objects' bytes, in the
    order of ``dtype`` (a packed structured type, one field per object).
    """

    fields: tuple[tuple[str, str], ...]  # (bank array, numpy type)
    rows: Index | slice  # bank slots (a slice when consecutive)
    index: Index
    dtype: np.dtype[np.void]
    buffer: npt.NDArray[np.void]  # scatter staging, preallocated
    # ``sim_slaves._pdlink``'s arguments after the memory, made on first use (see :func:`_c_args`)
    c_args: CArgs | None = None


@dataclass
class DriveLink:
    """Gather/scatter plan between chain memory and a drive bank, for the fast drives."""

    bank: DriveBank
    inputs: list[_Group] = field(default_factory=list)  # only drives whose ESC is in OP
    outputs: list[_Group] = field(default_factory=list)
    slots: Index = field(default_factory=lambda: np.zeros(0, dtype=np.intp))  # every fast drive

    def gather(self, memory: npt.NDArray[np.uint8]) -> None:
        """The master's outputs in memory -> the bank's input arrays (OP drives)."""
        bank = self.bank
        for g in self.inputs:
            rec = memory[g.index].view(g.dtype)[:, 0]
            for name, _ in g.fields:
                getattr(bank, name)[g.rows] = rec[name]

    def scatter(self, memory: npt.NDArray[np.uint8]) -> None:
        """The bank's output arrays -> memory (what the master reads)."""
        bank = self.bank
        for g in self.outputs:
            buf = g.buffer
            for name, _ in g.fields:
                buf[name] = getattr(bank, name)[g.rows]
            memory[g.index] = buf.view(np.uint8).reshape(g.index.shape)

    def gather_lean(self, memory: npt.NDArray[np.uint8]) -> None:
        """:meth:`gather` in one C call per group (``sim_slaves._pdlink`` where built, else :meth:`gather`)."""
        if pdlink is None:
            self.gather(memory)
            return
        for g in self.inputs:
            pdlink.gather(memory, *(g.c_args or _c_args(g, self.bank)))

    def scatter_lean(self, memory: npt.NDArray[np.uint8]) -> None:
        """:meth:`scatter` in one C call per group (``sim_slaves._pdlink`` where built, else :meth:`scatter`)."""
        if pdlink is None:
            self.scatter(memory)
            return
        for g in self.outputs:
            pdlink.scatter(memory, *(g.c_args or _c_args(g, self.bank)))

    def op_slots(self) -> set[int]:
        """Bank slots whose inputs come from memory."""
        out: set[int] = set()
        for g in self.inputs:
            rows = g.rows
            out.update(range(rows.start, rows.stop) if isinstance(rows, slice) else rows.tolist())
        return out


_KIND = {"u1": b"B", "i1": b"b", "<u2": b"H", "<i2": b"h", "<i4": b"i"}  # numpy type -> _pdlink's kind


def _c_args(g: _Group, bank: DriveBank) -> CArgs:
    """A group as ``sim_slaves._pdlink`` takes it: each object's first memory byte per drive (drives x
    objects), the drives' slots, the objects' kinds, the bank's arrays (kept in ``g.c_args``)."""
    first = np.cumsum([0, *(np.dtype(t).itemsize for _, t in g.fields)])[:-1]
    rows = g.rows
    slots = np.arange(rows.start, rows.stop) if isinstance(rows, slice) else rows
    g.c_args = (
        np.ascontiguousarray(g.index[:, first], dtype=np.int64),
        np.ascontiguousarray(slots, dtype=np.int64),
        b"".join(_KIND[t] for _, t in g.fields),
        tuple(getattr(bank, name) for name, _ in g.fields),
    )
    return g.c_args


def _groups(
    members: list[tuple[int, list[tuple[str, str, int]]]],
) -> list[_Group]:
    """``members``: (bank slot, [(array, type, memory address)]) -> groups by the objects they carry."""
    by_sig: dict[tuple[tuple[str, str], ...], list[tuple[int, list[int]]]] = {}
    for slot, objs in members:
        if not objs:
            continue
        sig = tuple((a, t) for a, t, _ in objs)
        idx = [addr + k for _, t, addr in objs for k in range(np.dtype(t).itemsize)]
        by_sig.setdefault(sig, []).append((slot, idx))
    groups = []
    for sig, rows in by_sig.items():
        slots = np.array([r for r, _ in rows], dtype=np.intp)
        consecutive = bool(len(slots) and (np.diff(slots) == 1).all())
        dtype = np.dtype([(name, t) for name, t in sig])
        groups.append(
            _Group(
                fields=sig,
                rows=slice(int(slots[0]), int(slots[-1]) + 1) if consecutive else slots,
                index=np.array([i for _, i in rows], dtype=np.intp),
                dtype=dtype,
                buffer=np.zeros(len(slots), dtype=dtype),
            )
        )
    return groups


def build_drive_link(
    bank: DriveBank,
    entries: Sequence[tuple[int, int, Esc, dict[int, tuple[int, str]], dict[int, tuple[int, str]]]],
) -> DriveLink:
    """``entries``: (bank slot, wire index, slave, output offsets, input offsets) per fast drive.

    Offsets as :func:`pdo_offsets` gives them; memory bases are the slaves'
    SM2 (outputs) and SM3 (inputs) start addresses. Inputs of a slave not in
    OP stay out (its drive keeps what its OD says, as an ESC outside OP does
    not hand outputs to the application).
    """
    gathers: list[tuple[int, list[tuple[str, str, int]]]] = []
    scatters: list[tuple[int, list[tuple[str, str, int]]]] = []
    for slot, wire, esc, outs, ins in entries:
        base_out = wire * MEM_SIZE + esc.sm[2][0]
        base_in = wire * MEM_SIZE + esc.sm[3][0]
        if esc.state == AlState.OP:
            gathers.append(
                (
                    slot,
                    [
                        (a, t, base_out + outs[i][0])
                        for i, a, t in DRIVE_INPUTS
                        if outs.get(i, (0, ""))[1] == t
                    ],
                )
            )
        scatters.append(
            (slot, [(a, t, base_in + ins[i][0]) for i, a, t in DRIVE_OUTPUTS if ins.get(i, (0, ""))[1] == t])
        )
    return DriveLink(
        bank,
        inputs=_groups(gathers),
        outputs=_groups(scatters),
        slots=np.array([e[0] for e in entries], dtype=np.intp),
    )
