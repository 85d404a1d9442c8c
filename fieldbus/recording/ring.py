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
:attr:`Ring.common` and :class:`BusColumns`: derived from the CycleResult and BusStatus dataclasses), per bus the per-slave fresh flags (and NMT
states on CANopen), per axis group the bytes of its output and input images
(engineering values and wire bytes as :class:`~fieldbus.core.pdo.image.DirectionImage`
lays them out). Copies use ``struct.pack_into`` and memoryview slices over
preallocated arrays (no numpy call per cycle): nothing is allocated that
outlives the call.
"""

from __future__ import annotations

import struct
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from operator import attrgetter
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from fieldbus.core.status_fields import NO_VALUE, Carry, StatusField, of, text

if TYPE_CHECKING:
    from fieldbus.backends.base import AxisGroup, Backend
    from fieldbus.recording.source import BusStatus, CycleResult, Operational

OWN = ("cycle", "t_ns", "wakeup_ns")  # the /cycle columns the ring sets itself (cycle: CycleResult.cycle - 1)
# CycleResult fields not in the /cycle row (its numbers are: derived from the dataclass), and where they are
CYCLE_EXCLUDED = {
    "cycle": "column 'cycle': the index of the cycle run (CycleResult.cycle - 1)",
    "buses": "the /bus/<bus> channels",
    "events": "/events",
    "drive_faults": "'drive_fault' events",
    "_by_name": "an index of buses",
}
EMERGENCIES = "emergencies"  # a bus column that is not a BusStatus field: the backend's EMCY count
# BusStatus fields the ring does not carry per cycle, and where the recording keeps them instead
EXCLUDED = {
    "name": "channel metadata 'bus' (constant)",
    "expected_wkc": "channel metadata 'expected_wkc' (constant)",
    "error": "'bus_error' events (the cycle's BusEvent)",
    "last_error": "'bus_error' events (the cycle's BusEvent)",
    "last_fault": "'fault' events (the newest of them)",
}
TEXTS = 64  # texts kept per bus and text field (by its change count % TEXTS)


@dataclass(frozen=True)
class BusColumns:
    """The int64 columns of one bus in the ring, derived from its status class (see
    :mod:`fieldbus.core.status_fields`): each NUMBER field, :data:`EMERGENCIES`, then per TEXT field
    ``<name>_seq``, the count of its changes (the texts are kept in :attr:`Ring.texts`)."""

    numbers: tuple[StatusField, ...]  # BusStatus fields, one column each, in the dataclass's order
    texts: tuple[str, ...]  # BusStatus TEXT fields (their changes become events of that kind)

    @classmethod
    def of(cls, status_cls: type) -> BusColumns:
        return cls(
            of(status_cls, Carry.NUMBER, exclude=EXCLUDED),
            tuple(f.name for f in of(status_cls, Carry.TEXT, exclude=EXCLUDED)),
        )

    @property
    def names(self) -> tuple[str, ...]:
        return (*(f.name for f in self.numbers), EMERGENCIES, *(f"{t}_seq" for t in self.texts))

    @property
    def recorded(self) -> tuple[str, ...]:
        """The columns that go to the file's bus rows (the change counts stay in the ring)."""
        return (*(f.name for f in self.numbers), EMERGENCIES)

    def index(self, name: str) -> int:
        return self.names.index(name)


@dataclass
class BusSlot:
    """One bus's place in the ring."""

    index: int  # of the bus in the network
    base: int  # first column of the bus in the int64 row
    offset: int  # its byte offset in the row (base * 8)
    status: BusStatus
    backend: Backend
    fresh: npt.NDArray[np.bool_]  # (rows, slaves)
    nmt: npt.NDArray[np.int16] | None  # (rows, slaves): CANopen heartbeat states
    nmt_src: npt.NDArray[np.int16] | None
    has_emcy: bool
    last_texts: list[object]  # per TEXT field, its value last seen (compared by identity)
    text_seq: list[int]  # per TEXT field, its changes so far


@dataclass
class GroupSlot:
    """One axis group's place in the ring: its image bytes, outputs then inputs."""

    group: AxisGroup
    out: npt.NDArray[np.uint8]  # (rows, axes * out itemsize)
    inp: npt.NDArray[np.uint8]
    out_src: npt.NDArray[np.uint8]  # the output image's buffer (values and wire bytes), flat
    in_src: npt.NDArray[np.uint8]


def _numbers_of(fields: tuple[StatusField, ...]) -> Callable[[Any], tuple[int, ...]]:
    """A function of a status (BusStatus, CycleResult) giving its NUMBER ``fields`` as ints (``None``:
    :data:`NO_VALUE`).

    Compiled from the field names (identifiers of the dataclass) into one tuple expression, as
    :mod:`dataclasses` compiles ``__init__``: the cycle reads each field once, with no loop.
    """
    items = ", ".join(
        f"(NO_VALUE if st.{f.name} is None else st.{f.name})" if f.optional else f"st.{f.name}"
        for f in fields
    )
    assert all(f.name.isidentifier() for f in fields)
    code = f"lambda st: ({items},)"
    fn: Callable[[Any], tuple[int, ...]] = eval(code, {"NO_VALUE": NO_VALUE})
    return fn


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
        backends = [v.backend for v in op.buses]
        # the columns, derived from the classes of the network's own CycleResult and BusStatus objects
        self.cycle_numbers = of(type(op.result), Carry.NUMBER, exclude=CYCLE_EXCLUDED)
        self.common = common = (*OWN, *(f.name for f in self.cycle_numbers))
        statuses = op.result.buses
        self.columns = cols = BusColumns.of(type(statuses[0])) if statuses else BusColumns((), ())
        n_bus = len(cols.names)
        self.width = len(common) + n_bus * len(backends)
        self.ints = np.zeros((rows, self.width), dtype=np.int64)
        self.row_bytes = self.width * 8
        self._buf = _flat_bytes(self.ints).data  # struct.pack_into targets: no numpy scalars
        self._pack_common = struct.Struct(f"<{len(common)}q").pack_into
        self._pack_bus = struct.Struct(f"<{n_bus}q").pack_into
        self.buses: list[BusSlot] = []
        for k, (b, st) in enumerate(zip(backends, op.result.buses, strict=True)):
            nmt_src = b.nmt_state
            if not (isinstance(nmt_src, np.ndarray) and nmt_src.dtype == np.int16):
                nmt_src = None
            self.buses.append(
                BusSlot(
                    index=k,
                    base=len(common) + n_bus * k,
                    offset=8 * (len(common) + n_bus * k),
                    status=st,
                    backend=b,
                    fresh=np.zeros((rows, b.n_slaves), dtype=bool),
                    nmt=None if nmt_src is None else np.zeros((rows, b.n_slaves), dtype=np.int16),
                    nmt_src=nmt_src,
                    has_emcy=True,  # every backend counts its emergencies (Backend.emcy_count)
                    last_texts=[getattr(st, t) for t in cols.texts],
                    text_seq=[0] * len(cols.texts),
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
        # what capture() copies per row: (the ring's flat bytes, the source's bytes, bytes per row)
        pairs: list[tuple[npt.NDArray[Any], npt.NDArray[Any]]] = []
        for slot in self.buses:
            pairs.append((slot.fresh, slot.status.fresh))
            if slot.nmt is not None and slot.nmt_src is not None:
                pairs.append((slot.nmt, slot.nmt_src))
        for gs in self.groups:
            pairs += [(gs.out, gs.out_src), (gs.inp, gs.in_src)]
        self._copies = tuple(
            (_flat_bytes(dst).data, _flat_bytes(src).data, _flat_bytes(src).size) for dst, src in pairs
        )
        # per bus and TEXT field, a small ring of its texts (by its change count % TEXTS)
        self.texts: list[list[list[str | None]]] = [[[None] * TEXTS for _ in cols.texts] for _ in backends]
        self.wakeup_ns = NO_VALUE  # set before the cycle by whoever measures it (run_cycles' tap)
        self.noted: deque[dict[str, Any]] = deque()  # events the cycle saw (note()), in cycle order
        self.count = 0  # cycles captured: written by the cycle only
        self.stopped = False  # set by the recorder: capture() does nothing any more
        self.capture = self._compile_capture()  # what exchange() calls (through the recorder) each cycle
        # the counters and NMT states as recording begins (captured once into row 0, then row 0 is
        # free again): the events of the first recorded row compare with them, so a change in a
        # block the writer had to drop still shows up, at the first cycle recorded after it
        self.capture(op.result, 0)
        self.baseline = self.ints[0].copy()
        self.baseline_nmt = [None if s.nmt is None else s.nmt[0].copy() for s in self.buses]
        self.count = 0

    def _compile_capture(self) -> Callable[[CycleResult, int], None]:
        """:attr:`capture`: a closure over the ring's constants (no attribute look-ups but the counters)."""
        ring = self
        rows, row_bytes, buf = self.rows, self.row_bytes, self._buf
        pack_common, pack_bus = self._pack_common, self._pack_bus
        buses = tuple((s, s.status, s.offset, s.backend if s.has_emcy else None) for s in self.buses)
        copies = self._copies
        new_text = self._new_text
        no_value = NO_VALUE
        numbers = _numbers_of(self.columns.numbers)
        cycle_numbers = _numbers_of(self.cycle_numbers)
        texts = tuple(enumerate(attrgetter(t) for t in self.columns.texts))

        def capture(res: CycleResult, t0_ns: int) -> None:
            """Copy this cycle (``res``, started at ``t0_ns``) into the next row. Never blocks.

            About 2 us with warm caches, 5 us inside a cycle (one bus, one group of 12 axes): one
            ``struct.pack_into`` for the cycle's and one per bus's int64 fields, one memoryview slice
            copy per image (fresh flags, NMT states, output and input bytes); no numpy call, nothing kept.
            """
            if ring.stopped:
                return
            n = ring.count
            row = n % rows
            c = row * row_bytes
            pack_common(buf, c, res.cycle - 1, t0_ns, ring.wakeup_ns, *cycle_numbers(res))
            ring.wakeup_ns = no_value
            for slot, st, off, emcy in buses:
                last = slot.last_texts
                for j, get in texts:
                    v = get(st)
                    if v is not last[j]:
                        new_text(slot, j, v)
                pack_bus(buf, c + off, *numbers(st), -1 if emcy is None else emcy.emcy_count, *slot.text_seq)
            for dst, src, w in copies:  # one slice copy per image row
                o = row * w
                dst[o : o + w] = src
            ring.count = n + 1

        return capture

    def note(self, cycle: int, kind: str, **fields: Any) -> None:
        """An event the cycle saw at ``cycle`` (e.g. an SDO abort); the writer adds that cycle's ``t_ns``.

        Called from the cycle thread when the event happens (rare: it allocates the event).
        """
        if not self.stopped:
            self.noted.append({"cycle": cycle, "t_ns": 0, "kind": kind, **fields})

    def _new_text(self, slot: BusSlot, j: int, value: object) -> None:
        """TEXT field ``j`` of ``slot``'s status is a new object ``value`` (rare: its ``str()`` allocates).

        A new text counts (a recovery failing again with the same message is a new failure); a new
        structured value (a nested dataclass) counts when it differs from the last one.
        """
        last, slot.last_texts[j] = slot.last_texts[j], value
        if not (value is None or isinstance(value, str)) and value == last:
            return
        slot.text_seq[j] += 1
        self.texts[slot.index][j][slot.text_seq[j] % TEXTS] = text(value)

    # -- the writer's side ---------------------------------------------------------------
    def intact_from(self) -> int:
        """The oldest cycle whose row the cycle has not started to overwrite (it may be writing ``count``)."""
        return self.count - self.rows + 1

    def snapshot(self, start: int, stop: int, into: Snapshot | None = None) -> tuple[int, Snapshot | None]:
        """Copies of cycles ``[start, stop)`` (at most :attr:`rows`, all captured already).

        Returns ``(first, snap)``: the cycle overwrote the rows of cycles before
        ``first`` while (or before) they were copied, ``snap`` holds ``[first, stop)``
        (None when nothing is left). ``into``: copy into the first rows of these
        arrays (:meth:`buffers`; reused, so no fresh pages to fault in) and return
        views of them. One numpy call per stream (two where the range wraps).
        """
        n = stop - start
        if not 0 < n <= self.rows:
            raise ValueError(f"cannot copy cycles {start}..{stop} out of a ring of {self.rows} rows")
        lo = start % self.rows
        hi = lo + n
        rows = self.rows

        def take(a: npt.NDArray[Any], out: npt.NDArray[Any] | None) -> npt.NDArray[Any]:
            out = np.empty((n, *a.shape[1:]), dtype=a.dtype) if out is None else out[:n]
            if hi <= rows:
                np.copyto(out, a[lo:hi])
            else:
                np.copyto(out[: rows - lo], a[lo:])
                np.copyto(out[rows - lo :], a[: hi - rows])
            return out

        b = into
        snap = Snapshot(
            ints=take(self.ints, None if b is None else b.ints),
            fresh=[take(s.fresh, None if b is None else b.fresh[k]) for k, s in enumerate(self.buses)],
            nmt=[
                None if s.nmt is None else take(s.nmt, None if b is None else b.nmt[k])
                for k, s in enumerate(self.buses)
            ],
            out=[take(g.out, None if b is None else b.out[k]) for k, g in enumerate(self.groups)],
            inp=[take(g.inp, None if b is None else b.inp[k]) for k, g in enumerate(self.groups)],
        )
        # the cycle writes row `count` before it counts it: the rows of cycles from count - rows + 1 on are
        # intact now, so they were all along the copy
        first = max(start, self.intact_from())
        if first >= stop:
            return first, None
        return first, snap.tail(first - start)

    def buffers(self, n: int) -> Snapshot:
        """Arrays for :meth:`snapshot` ``into``, ``n`` rows each."""
        return Snapshot(
            ints=np.empty((n, self.width), dtype=np.int64),
            fresh=[np.empty((n, s.fresh.shape[1]), dtype=bool) for s in self.buses],
            nmt=[
                None if s.nmt is None else np.empty((n, s.nmt.shape[1]), dtype=np.int16) for s in self.buses
            ],
            out=[np.empty((n, g.out.shape[1]), dtype=np.uint8) for g in self.groups],
            inp=[np.empty((n, g.inp.shape[1]), dtype=np.uint8) for g in self.groups],
        )


@dataclass
class Snapshot:
    """Consecutive cycles copied out of the ring (the writer's private copy)."""

    ints: npt.NDArray[np.int64]  # (rows, width)
    fresh: list[npt.NDArray[np.bool_]]
    nmt: list[npt.NDArray[np.int16] | None]
    out: list[npt.NDArray[np.uint8]]
    inp: list[npt.NDArray[np.uint8]]

    @property
    def n(self) -> int:
        return int(self.ints.shape[0])

    def tail(self, k: int) -> Snapshot:
        """The same rows without the first ``k`` (views)."""
        if k == 0:
            return self
        return Snapshot(
            ints=self.ints[k:],
            fresh=[f[k:] for f in self.fresh],
            nmt=[None if m is None else m[k:] for m in self.nmt],
            out=[o[k:] for o in self.out],
            inp=[i[k:] for i in self.inp],
        )
