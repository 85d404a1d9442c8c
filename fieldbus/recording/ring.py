"""The cycle's side of a recording: a preallocated ring of rows the cycle copies into.

The ring holds ``block_cycles * ring_blocks`` rows. Cycle ``n`` (counted from
the start of the recording) goes to row ``n % rows``; rows ``[s * block_cycles,
(s + 1) * block_cycles)`` form block ``s``. The cycle only writes rows and then
advances :attr:`Ring.count`; the writer thread copies a block out once it is
complete and checks afterwards that the cycle has not started on that block's
rows again (a seqlock without a lock: the counter is written by the cycle
only). A writer that falls behind by a whole ring loses the oldest block; the
cycle never waits.

Per cycle and row: an int64 vector (cycle, times, per-bus status, see
:data:`COMMON` and :data:`BUS`), per bus the per-slave fresh flags (and NMT
states on CANopen), per axis group the bytes of its output and input images
(engineering values and wire bytes as :class:`~fieldbus.core.pdo.image.DirectionImage`
lays them out). Copies use ``np.copyto`` and a memoryview over preallocated
arrays: nothing is allocated that outlives the call.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from fieldbus.recording.schema import NO_VALUE

if TYPE_CHECKING:
    from fieldbus.backends.base import AxisGroup, Backend
    from fieldbus.network import BusStatus, CycleResult, Operational

COMMON = ("cycle", "t_ns", "wakeup_ns", "exchange_ns", "fresh", "safe_stop")
BUS = (
    "ran",
    "verdict",
    "wkc",
    "consecutive_misses",
    "safe_stop",
    "recovering",
    "recoveries",
    "dc_time_ns",
    "dc_sync_error_ns",
    "emergencies",
    "error_seq",  # counts changes of BusStatus.recovery_error; the texts are kept in Ring.texts
)
TEXTS = 64  # recovery error texts kept per bus (by error_seq % TEXTS)


@dataclass
class BusSlot:
    """One bus's place in the ring."""

    index: int  # of the bus in the network
    base: int  # first column of the bus in the int64 row
    status: BusStatus
    backend: Backend
    fresh: npt.NDArray[np.bool_]  # (rows, slaves)
    nmt: npt.NDArray[np.int16] | None  # (rows, slaves): CANopen heartbeat states
    nmt_src: npt.NDArray[np.int16] | None
    has_emcy: bool


@dataclass
class GroupSlot:
    """One axis group's place in the ring: its image bytes, outputs then inputs."""

    group: AxisGroup
    out: npt.NDArray[np.uint8]  # (rows, axes * out itemsize)
    inp: npt.NDArray[np.uint8]
    out_src: npt.NDArray[np.uint8]  # the output image's buffer (values and wire bytes), flat
    in_src: npt.NDArray[np.uint8]


def _flat_bytes(values: npt.NDArray[Any]) -> npt.NDArray[np.uint8]:
    assert values.flags.c_contiguous
    flat: npt.NDArray[np.uint8] = values.view(np.uint8).reshape(-1)
    return flat


class Ring:
    """Preallocated rows for ``block_cycles * ring_blocks`` cycles of ``op``; :meth:`capture` fills one."""

    def __init__(self, op: Operational, block_cycles: int, ring_blocks: int) -> None:
        if block_cycles < 1 or ring_blocks < 2:
            raise ValueError("block_cycles must be >= 1 and ring_blocks >= 2")
        self.block_cycles = block_cycles
        self.ring_blocks = ring_blocks
        self.rows = rows = block_cycles * ring_blocks
        backends = op._net.backends
        self.width = len(COMMON) + len(BUS) * len(backends)
        self.ints = np.zeros((rows, self.width), dtype=np.int64)
        self._mv = self.ints.reshape(-1).data  # a memoryview: item stores without numpy scalars
        self.buses: list[BusSlot] = []
        for k, (b, st) in enumerate(zip(backends, op.result.buses, strict=True)):
            nmt_src = getattr(b, "nmt_state", None)
            if not (isinstance(nmt_src, np.ndarray) and nmt_src.dtype == np.int16):
                nmt_src = None
            self.buses.append(
                BusSlot(
                    index=k,
                    base=len(COMMON) + len(BUS) * k,
                    status=st,
                    backend=b,
                    fresh=np.zeros((rows, b.n_slaves), dtype=bool),
                    nmt=None if nmt_src is None else np.zeros((rows, b.n_slaves), dtype=np.int16),
                    nmt_src=nmt_src,
                    has_emcy=isinstance(getattr(b, "emergencies", None), list),
                )
            )
        self.groups: list[GroupSlot] = []
        for b in backends:
            for g in b.groups:
                out_src = _flat_bytes(g.image.outputs.values)
                in_src = _flat_bytes(g.image.inputs.values)
                self.groups.append(
                    GroupSlot(
                        g,
                        np.zeros((rows, out_src.size), dtype=np.uint8),
                        np.zeros((rows, in_src.size), dtype=np.uint8),
                        out_src,
                        in_src,
                    )
                )
        # recovery errors: the last text seen per bus (by identity) and a small ring of texts
        self._last_error: list[str | None] = [st.recovery_error for st in op.result.buses]
        self._error_seq: list[int] = [0] * len(backends)
        self.texts: list[list[str | None]] = [[None] * TEXTS for _ in backends]
        self.wakeup_ns = NO_VALUE  # set before the cycle by whoever measures it (run_cycles' tap)
        self.count = 0  # cycles captured: written by the cycle only
        self.stopped = False  # set by the recorder: capture() does nothing any more

    def capture(self, res: CycleResult, t0_ns: int) -> None:
        """Copy this cycle (``res``, started at ``t0_ns``) into the next row. Never blocks."""
        if self.stopped:
            return
        n = self.count
        row = n % self.rows
        mv = self._mv
        c = row * self.width
        mv[c] = res.cycle - 1
        mv[c + 1] = t0_ns
        mv[c + 2] = self.wakeup_ns
        self.wakeup_ns = NO_VALUE
        mv[c + 3] = res.exchange_ns
        mv[c + 4] = res.fresh
        mv[c + 5] = res.safe_stop
        for slot in self.buses:
            st = slot.status
            j = c + slot.base
            mv[j] = st.ran
            mv[j + 1] = st.verdict
            mv[j + 2] = st.wkc
            mv[j + 3] = st.consecutive_misses
            mv[j + 4] = st.safe_stop
            mv[j + 5] = st.recovering
            mv[j + 6] = st.recoveries
            dc = st.dc_time_ns
            mv[j + 7] = NO_VALUE if dc is None else dc
            dc = st.dc_sync_error_ns
            mv[j + 8] = NO_VALUE if dc is None else dc
            mv[j + 9] = len(slot.backend.emergencies) if slot.has_emcy else -1  # type: ignore[attr-defined]
            err = st.recovery_error
            k = slot.index
            if err is not self._last_error[k]:
                self._last_error[k] = err
                seq = self._error_seq[k] + 1
                self._error_seq[k] = seq
                self.texts[k][seq % TEXTS] = err
            mv[j + 10] = self._error_seq[k]
            np.copyto(slot.fresh[row], st.fresh)
            if slot.nmt_src is not None and slot.nmt is not None:
                np.copyto(slot.nmt[row], slot.nmt_src)
        for g in self.groups:
            np.copyto(g.out[row], g.out_src)
            np.copyto(g.inp[row], g.in_src)
        self.count = n + 1

    # -- the writer's side ---------------------------------------------------------------
    def snapshot(self, start: int, stop: int) -> Snapshot | None:
        """Copies of cycles ``[start, stop)`` (one block at most), or None when the cycle overwrote them meanwhile."""
        if self.count >= start + self.rows:
            return None
        lo = start % self.rows
        hi = lo + (stop - start)
        snap = Snapshot(
            ints=self.ints[lo:hi].copy(),
            fresh=[s.fresh[lo:hi].copy() for s in self.buses],
            nmt=[None if s.nmt is None else s.nmt[lo:hi].copy() for s in self.buses],
            out=[g.out[lo:hi].copy() for g in self.groups],
            inp=[g.inp[lo:hi].copy() for g in self.groups],
        )
        # the cycle writes row `count` before it counts it: rows of this block are intact while
        # the cycle has not reached start + rows (where it writes this block's first row again)
        if self.count >= start + self.rows:
            return None
        return snap


@dataclass
class Snapshot:
    """One block copied out of the ring (the writer's private copy)."""

    ints: npt.NDArray[np.int64]  # (rows, width)
    fresh: list[npt.NDArray[np.bool_]]
    nmt: list[npt.NDArray[np.int16] | None]
    out: list[npt.NDArray[np.uint8]]
    inp: list[npt.NDArray[np.uint8]]

    @property
    def n(self) -> int:
        return int(self.ints.shape[0])
