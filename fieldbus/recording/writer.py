"""The recorder: a ring the cycle copies into, a writer thread that turns full blocks into MCAP messages.

Why MCAP with numpy rows: one message per block of cycles (256 by default) is
one ``write`` per block and loads with ``np.frombuffer`` - no per-cycle
encoding on either side; any MCAP tool lists, splits and merges the file, and
the schema record of each channel carries the numpy dtype and the meaning of
every field (:mod:`fieldbus.recording.schema`). Events are JSON with a JSON
schema, readable in any MCAP viewer. Messages are not chunked: the records of a
block are gathered in memory (:class:`_Sink`) and go to disk in one ``write``
and a flush, so a file cut short loads up to its last complete block.

The writer thread takes no lock the cycle takes: the cycle advances a counter,
the writer reads it (see :mod:`fieldbus.recording.ring`). It holds the GIL the
cycle needs, so it does little and seldom: it wakes every :data:`POLL_S` and
waits until a quarter of the ring is complete (4 blocks: about 1 s at 1 kHz),
then copies up to half the ring out and converts it at once into reused
arrays (a few dozen numpy calls per batch, not per block: about 1.5 us of
CPU per cycle for 12 axes), and writes it block by block.
"""

from __future__ import annotations

import errno
import io
import json
import threading
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any, cast

import numpy as np
import numpy.typing as npt

from fieldbus.core.status_fields import event_fields
from fieldbus.errors import BackendUnavailableError, FieldbusError
from fieldbus.recording import schema
from fieldbus.recording.events import EventDeriver
from fieldbus.recording.ring import Ring, Snapshot

if TYPE_CHECKING:
    from fieldbus.recording.source import CycleResult, Operational

BLOCK_CYCLES = 256
RING_BLOCKS = 16
# the cycle's events as recording events: every field of the event's dataclass (derived, as
# fieldbus.core.status_fields.event_fields), renamed where the event schema names it otherwise
EVENT_RENAMED = {"reason": "name"}  # OutputClamp.reason (NAN, INF, RANGE, STEP)
EVENT_EXCLUDED = ("cycle", "kind")  # the recording event's own ``cycle`` and ``kind``
NOTED_KINDS = (
    "bus_error",
    "acyclic_error",
    "esc_errors",
    "link_down",
    "link_up",
    "sdo_abort",
)  # BusEvents (others: rows)
POLL_S = 0.05  # the writer looks for full blocks this often, s (a 16-block ring lasts 0.5 s at 8 kHz)


class RecordingWarning(UserWarning):
    """The recording stopped (a write failed); the cycle goes on."""


def _describe(exc: OSError) -> str:
    return exc.strerror or errno.errorcode.get(exc.errno or 0, "") or str(exc)


def check_writable(path: str | Path) -> Path:
    """Create (truncate) ``path`` for a recording now, before any bus starts; :class:`FieldbusError` naming it if not."""
    p = Path(path)
    try:
        with open(p, "wb"):
            pass
    except OSError as exc:
        raise FieldbusError(f"cannot record to {p}: {_describe(exc)}") from None
    return p


def _open(path: Path) -> IO[bytes]:
    return open(path, "wb")


def _data(arr: npt.NDArray[Any]) -> bytes:
    """A contiguous array's bytes without a copy (the mcap writer copies them into its record)."""
    view: bytes = arr.view(np.uint8).data  # type: ignore[assignment]
    return view


class _Sink:
    """What the mcap writer writes to: its records are kept until :meth:`drain` writes them in one call."""

    def __init__(self, f: IO[bytes]) -> None:
        self.f = f
        self.parts: list[bytes] = []
        self.pos = 0  # bytes written by the mcap writer so far (its tell())

    def write(self, data: bytes) -> int:
        self.parts.append(data)  # the mcap writer hands over a fresh bytes object per record
        self.pos += len(data)
        return len(data)

    def tell(self) -> int:
        return self.pos

    def flush(self) -> None:
        self.drain()

    def drain(self) -> None:
        """Write what was gathered (one ``write``), flush the file."""
        parts = self.parts
        if parts:
            data = parts[0] if len(parts) == 1 else b"".join(parts)
            parts.clear()
            self.f.write(data)
        self.f.flush()


class Recorder:
    """Records every cycle of ``op`` to the MCAP file ``path`` until :meth:`close` (or ``op.close()``).

    ``raw``: also the wire bytes of every axis. ``block_cycles`` cycles form one
    message; the ring holds ``ring_blocks`` blocks (a writer that falls a whole
    ring behind drops the oldest block: :attr:`dropped_blocks`). ``open_file``
    opens the path for writing (binary; tests pass a failing one).
    """

    def __init__(
        self,
        op: Operational,
        path: str | Path,
        *,
        raw: bool = False,
        block_cycles: int = BLOCK_CYCLES,
        ring_blocks: int = RING_BLOCKS,
        open_file: Callable[[Path], IO[bytes]] | None = None,
    ) -> None:
        try:
            from mcap.writer import CompressionType, Writer
        except ImportError:
            raise BackendUnavailableError("recording needs mcap: pip install 'fieldbus[record]'") from None
        from fieldbus.version import __version__

        self.path = Path(path)
        self.raw = raw
        self.ring = Ring(op, block_cycles, ring_blocks)
        self.capture: Callable[[CycleResult, int], None] = self.ring.capture  # what exchange() calls
        self._events = EventDeriver(self.ring)
        self.dropped_blocks = 0  # blocks the writer lost because the cycle overwrote them first
        self.blocks = 0  # block messages written per stream
        self.cycles = 0  # cycles written
        self.error: BaseException | None = None  # why the recording stopped early
        self._op = op
        self._closed = False
        self._closing = False
        self._in_dtypes = [g.group.image.inputs.values.dtype for g in self.ring.groups]
        self._out_dtypes = [g.group.image.outputs.values.dtype for g in self.ring.groups]
        self._file: IO[bytes] | None = None
        try:
            f = (open_file or _open)(self.path)
            # a raw file gets our buffer (mcap would add its own, which our per-block flush would not reach)
            self._file = io.BufferedWriter(f) if isinstance(f, io.RawIOBase) else f
            self._sink = _Sink(self._file)
            w = self._mcap = Writer(
                cast(IO[bytes], self._sink), use_chunking=False, compression=CompressionType.NONE
            )
            w.start(profile="fieldbus", library=f"fieldbus {__version__}")
            self._setup(w, op)
            self._batch = self.ring.block_cycles * max(1, ring_blocks // 2)  # cycles written at most at once
            self._rows = self._row_buffers(self._batch)
            self._sink.drain()
        except OSError as exc:
            self._close_file()
            raise FieldbusError(f"cannot record to {self.path}: {_describe(exc)}") from None
        self._thread = threading.Thread(
            target=self._run, name=f"fieldbus-record {self.path.name}", daemon=True
        )
        self._thread.start()
        op.add_observer(self)

    # -- file layout ---------------------------------------------------------------------
    def _channel(self, w: Any, topic: str, dtype: np.dtype[Any], fields: dict[str, str], **meta: str) -> int:
        sid = w.register_schema(
            name=f"fieldbus.{topic.strip('/').split('/')[0]}",
            encoding=schema.SCHEMA_ENCODING,
            data=schema.schema_data(dtype, fields),
        )
        return int(
            w.register_channel(
                topic=topic,
                message_encoding=schema.MESSAGE_ENCODING,
                schema_id=sid,
                metadata={"dtype": schema.dtype_to_json(dtype), **meta},
            )
        )

    def _setup(self, w: Any, op: Operational) -> None:
        net = op.network
        self._cycle_dtype = schema.cycle_dtype(self.ring.cycle_numbers)
        self._cycle_ch = self._channel(w, "/cycle", self._cycle_dtype, schema.CYCLE_FIELDS)
        self._bus_dtypes: list[np.dtype[Any]] = []
        self._bus_ch: list[int] = []
        for slot in self.ring.buses:
            b = slot.backend
            dt = schema.bus_dtype(b.n_slaves, nmt=slot.nmt is not None, numbers=self.ring.columns.numbers)
            self._bus_dtypes.append(dt)
            self._bus_ch.append(
                self._channel(
                    w, f"/bus/{b.bus.name}", dt, schema.bus_fields(dt), bus=b.bus.name, type=b.kind,
                    slaves=json.dumps([a.slave.name for a in b.areas]), expected_wkc=str(b.expected_wkc),
                    cycle_time_us=str(b.bus.cycle_time_us),
                )
            )  # fmt: skip
        self._group_dtypes: list[np.dtype[Any]] = []
        self._group_ch: list[int] = []
        for g, bus in zip(self.ring.groups, self._events.groups, strict=True):
            img = g.group.image
            dt = schema.group_dtype(img.outputs, img.inputs, raw=self.raw)
            self._group_dtypes.append(dt)
            units = {
                d: {
                    e.name: e.channel.unit or ""
                    for e in (img.outputs if d == "outputs" else img.inputs).layout.channels
                }
                for d in ("outputs", "inputs")
            }
            self._group_ch.append(
                self._channel(
                    w, f"/group/{g.group.name}", dt, schema.GROUP_FIELDS, group=g.group.name, bus=bus.bus,
                    axes=json.dumps(list(bus.axes)), units=json.dumps(units),
                )
            )  # fmt: skip
        sid = w.register_schema(
            name="fieldbus.event",
            encoding="jsonschema",
            data=json.dumps(schema.event_schema(self.ring.columns.texts)).encode(),
        )
        self._event_ch = int(w.register_channel(topic="/events", message_encoding="json", schema_id=sid))
        w.add_metadata(
            "fieldbus",
            {
                "format": schema.FORMAT,
                "network": str(net.model.source),
                "cycle_time_us": str(op.cycle_time_us),
                "raw": json.dumps(self.raw),
                "block_cycles": str(self.ring.block_cycles),
                "start_unix_ns": str(time.time_ns()),
                "start_monotonic_ns": str(time.perf_counter_ns()),
            },
        )

    # -- the writer thread -------------------------------------------------------------------
    def _run(self) -> None:
        ring = self.ring
        size = ring.block_cycles
        batch = self._batch
        least = size * max(1, ring.ring_blocks // 4)  # cycles to wait for (fewer, bigger numpy calls)
        bufs = ring.buffers(batch)  # reused: the copy and the conversion touch the same pages every time
        nxt = 0  # first cycle (of the recording) not written yet; a multiple of size until the last block
        lost = 0  # cycles dropped since the last block written
        try:
            while True:
                closing = self._closing
                count = ring.count
                # whole blocks only, but everything when closing (the cycle has stopped)
                stop = min(count if closing else count - count % size, nxt + batch)
                if stop >= nxt + least or (closing and stop > nxt):
                    first, snap = ring.snapshot(nxt, stop, bufs)
                    if first > nxt:  # overwritten meanwhile: drop whole blocks up to `first`
                        cut = min(stop, nxt + -(-(first - nxt) // size) * size)
                        self.dropped_blocks += -(-(cut - nxt) // size)
                        lost += cut - nxt
                        snap = None if snap is None or cut >= stop else snap.tail(cut - first)
                    if snap is not None:
                        self._write(snap, lost)
                        lost = 0
                    nxt = stop
                    continue  # more may be complete already
                if closing:
                    break
                time.sleep(POLL_S)
            self._finish()
        except Exception as exc:
            self.error = exc
            ring.stopped = True
            warnings.warn(
                RecordingWarning(f"recording to {self.path} stopped after {self.cycles} cycles: {exc}; "
                                 "the cycle goes on"),
                stacklevel=1,
            )  # fmt: skip
            self._close_file()

    def _write(self, snap: Snapshot, lost: int) -> None:
        """Cycles of whole blocks (the last one may be short on close): converted at once (few numpy calls,
        each of which may release the GIL and wait for it again), written one block at a time (one message
        per stream and block, one write and flush per block: a cut file keeps every whole block)."""
        n = snap.n
        ints = snap.ints
        cyc_rows, bus_rows, group_rows = self._rows
        cyc = cyc_rows[:n]  # every field of these rows is written below
        for j, name in enumerate(self.ring.common):
            cyc[name] = ints[:, j]
        streams: list[tuple[int, npt.NDArray[Any]]] = [(self._cycle_ch, cyc)]
        for k, slot in enumerate(self.ring.buses):
            arr = bus_rows[k][:n]
            arr["cycle"] = cyc["cycle"]
            for j, name in enumerate(self.ring.columns.recorded):
                arr[name] = ints[:, slot.base + j]
            arr["fresh"] = snap.fresh[k]
            nmt = snap.nmt[k]
            if nmt is not None:
                arr["nmt_state"] = nmt
            streams.append((self._bus_ch[k], arr))
        inputs: list[npt.NDArray[Any]] = []
        for k, g in enumerate(self.ring.groups):
            arr = group_rows[k][:n]
            arr["cycle"] = cyc["cycle"]
            for d, rows, dt in (
                ("outputs", snap.out[k], self._out_dtypes[k]),
                ("inputs", snap.inp[k], self._in_dtypes[k]),
            ):
                values = rows.view(dt)  # (n, axes): the image rows as the cycle saw them
                arr[d] = values  # field by field, by position (the packed dtype lists them in the same order)
                if d == "inputs":
                    inputs.append(values)
                if self.raw:
                    img = g.group.image.outputs if d == "outputs" else g.group.image.inputs
                    arr[f"{d}_wire"] = rows.reshape(n, img.n_axes, dt.itemsize)[:, :, : img.layout.size]
            streams.append((self._group_ch[k], arr))
        cycles = cyc["cycle"]
        t_ns = cyc["t_ns"]
        events = self._events.block(snap, inputs)
        events += self._cycle_events(cycles, t_ns)
        if lost:
            events.append({"cycle": int(cycles[0]), "t_ns": int(t_ns[0]), "kind": "gap", "detail": f"{lost} "
                           "cycles before this one were not recorded (the writer fell a whole ring behind)"})  # fmt: skip
        events.sort(key=lambda e: e["cycle"])
        w = self._mcap
        size = self.ring.block_cycles
        e = 0
        for a in range(0, n, size):
            b = min(n, a + size)
            t0 = int(t_ns[a])
            seq = self.blocks
            for ch, arr in streams:
                w.add_message(ch, t0, _data(arr[a:b]), t0, seq)
            last = int(cycles[b - 1])
            while e < len(events) and events[e]["cycle"] <= last:
                ev = events[e]
                w.add_message(self._event_ch, ev["t_ns"], json.dumps(ev).encode(), ev["t_ns"], 0)
                e += 1
            self._sink.drain()  # the block's records in one write
            self.blocks += 1
            self.cycles += b - a

    def _row_buffers(self, n: int) -> tuple[npt.NDArray[Any], list[npt.NDArray[Any]], list[npt.NDArray[Any]]]:
        """The file's rows for ``n`` cycles, per stream: /cycle, each /bus, each /group (reused per batch)."""
        return (
            np.zeros(n, self._cycle_dtype),
            [np.zeros(n, dt) for dt in self._bus_dtypes],
            [np.zeros(n, dt) for dt in self._group_dtypes],
        )

    def _cycle_events(self, cycles: npt.NDArray[Any], t_ns: npt.NDArray[Any]) -> list[dict[str, Any]]:
        """Events the cycle noted (:meth:`Ring.note`) up to the last of ``cycles``, with their cycle's start."""
        noted = self.ring.noted
        last = int(cycles[-1])
        out: list[dict[str, Any]] = []
        while noted and noted[0]["cycle"] <= last:
            ev = noted.popleft()
            k = int(np.searchsorted(cycles, ev["cycle"]))
            if k < cycles.size and int(cycles[k]) == ev["cycle"]:
                ev["t_ns"] = int(t_ns[k])
            else:  # its cycle was not recorded (dropped): it goes with the next one recorded
                ev["cycle"], ev["t_ns"] = (
                    int(cycles[min(k, cycles.size - 1)]),
                    int(t_ns[min(k, cycles.size - 1)]),
                )
            out.append(ev)
        return out

    def _finish(self) -> None:
        self._mcap.add_metadata(
            "fieldbus.stats",
            {
                "cycles": str(self.cycles),
                "blocks": str(self.blocks),
                "dropped_blocks": str(self.dropped_blocks),
            },
        )
        self._mcap.finish()  # type: ignore[no-untyped-call]
        self._sink.drain()
        self._close_file(raise_errors=True)

    def _close_file(self, *, raise_errors: bool = False) -> None:
        f, self._file = self._file, None
        if f is None:
            return
        try:
            f.close()
        except OSError:
            if raise_errors:
                raise

    # -- the handle --------------------------------------------------------------------------
    @property
    def active(self) -> bool:
        """Cycles are still being recorded (not closed, no write failed)."""
        return not self.ring.stopped

    def note_events(self, events: list[Any]) -> None:
        """The cycle's drive faults, refused outputs, SDO aborts and bus errors as events in the recording
        (the cycle calls it)."""
        from fieldbus.core.drivefault import DriveFault
        from fieldbus.core.output_rules import OutputClamp

        for e in events:
            if isinstance(e, DriveFault):
                fields = event_fields(e, EVENT_RENAMED, EVENT_EXCLUDED)
                fields["name"] = e.name  # the error code's name
                self.ring.note(e.cycle, "drive_fault", **fields)
            elif isinstance(e, OutputClamp):
                self.ring.note(e.cycle, "output_clamp", **event_fields(e, EVENT_RENAMED, EVENT_EXCLUDED))
            elif e.kind in NOTED_KINDS:
                self.ring.note(e.cycle, e.kind, **event_fields(e, EVENT_RENAMED, EVENT_EXCLUDED))

    def close(self) -> None:
        """Stop recording, write what the ring holds, finish the file. Idempotent; never raises for the file
        (a failed write was already warned about: :attr:`error`)."""
        if self._closed:
            return
        self._closed = True
        self.ring.stopped = True  # the cycle copies nothing more
        self._op.remove_observer(self)
        self._closing = True
        self._thread.join()

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
