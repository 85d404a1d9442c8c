"""Every cycle the master ran, kept for assertions and for comparing two runs bit for bit.

A :class:`Trace` is filled by the emulation after each ``exchange()`` (the
user's loop does not change): per cycle whether every bus was fresh, the
safe-stop latch, per bus the verdict, working counter and per-slave
freshness and every other number of its ``BusStatus`` (:meth:`Trace.status`,
derived from the dataclass: a field added there is kept here too) and the
changes of its text fields (:meth:`Trace.texts`), per axis group the inputs (as decoded this cycle) and the
outputs (as this cycle's frame sent them), and every event of the cycle
(:attr:`CycleResult.events <fieldbus.CycleResult>`: drive faults, safe stop,
release, bus errors, whatever else a cycle reports) plus a ``recovered``
event when a bus's recovery brought a slave back. Arrays grow in chunks; the
cycle index is the position in them (0 = the first cycle after bring-up; it
equals ``CycleResult.cycle`` before that cycle's ``exchange()``).

Row k of the outputs is what cycle k sent: on the cycle the safe stop latches
the row still holds the controller's values (that frame left before the
misses were judged); the safe outputs appear from the next row on::

    at = assert_safe_stop_latched(trace, within=12, since=since)
    assert (trace.outputs("arm")["controlword"][at + 1] == 0x0002).all()  # quick stop from the next frame
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from fieldbus.core.status_fields import NO_VALUE, Carry, of, text
from fieldbus.errors import FieldbusError

if TYPE_CHECKING:
    from fieldbus.network import CycleResult, Network, Operational

CHUNK = 4096  # cycles added to the arrays at a time
# BusStatus fields the trace keeps elsewhere than :meth:`Trace.status` / :meth:`Trace.texts`
EXCLUDED = {
    "name": "Trace.bus_names",
    "expected_wkc": "constant: the network's (Network.model)",
    "fresh": "Trace.slave_fresh (per slave)",
}


def _zeros(shape: tuple[int, ...], dtype: Any) -> npt.NDArray[Any]:
    """Zeros, padding bytes of a structured dtype included (``np.zeros`` may leave those as they were),
    so that two equal traces are equal byte for byte."""
    dt = np.dtype(dtype)
    out: npt.NDArray[Any] = (
        np.zeros(int(np.prod(shape)) * dt.itemsize, dtype=np.uint8).view(dt).reshape(shape)
    )
    return out


def event_kind(event: object) -> str:
    """The kind of a cycle event: its ``kind`` text (``BusEvent``: ``safe_stop``, ``released``,
    ``bus_error``, ``acyclic_error``, ``recovered``), ``drive_fault`` for a ``DriveFault`` (raw-CAN
    motor faults too), else its class name in snake case (``ClampEvent`` -> ``clamp_event``)."""
    from fieldbus.core.drivefault import DriveFault

    kind = getattr(event, "kind", None)
    if isinstance(kind, str):
        return kind
    if isinstance(event, DriveFault):
        return "drive_fault"
    return re.sub(r"(?<!^)(?=[A-Z])", "_", type(event).__name__).lower()


@dataclass(frozen=True)
class TraceEvent:
    """An event of the cycle at trace row ``cycle``: ``event`` as the cycle reported it."""

    cycle: int
    kind: str
    event: object

    def __str__(self) -> str:
        return f"cycle {self.cycle}: {self.kind}: {self.event}"


class Trace:
    """Per-cycle record of an :class:`~fieldbus.network.Operational` (see the module)."""

    def __init__(self, op: Operational, network: Network) -> None:
        self._op = op
        self.bus_names = tuple(st.name for st in op.result.buses)
        self.group_names = tuple(op.groups)
        self._group_bus: dict[str, int] = {}
        self._group_rows: dict[str, npt.NDArray[np.intp]] = {}
        for name, g in op.groups.items():
            bus_name = next(b.bus.name for b in network.backends if g in b.groups)
            self._group_bus[name] = self.bus_names.index(bus_name)
            rows = np.arange(g.first, g.first + len(g.slaves))  # a multi-axis slave: a row per axis
            self._group_rows[name] = np.repeat(rows, g.image.n_axes // len(g.slaves))
        self.n = 0
        self._cap = 0
        self._fresh = np.zeros(0, dtype=bool)
        self._stop = np.zeros(0, dtype=bool)
        self._verdict = np.zeros((0, len(self.bus_names)), dtype=np.int8)
        self._wkc = np.zeros((0, len(self.bus_names)), dtype=np.int32)
        self._slave_fresh = [np.zeros((0, st.fresh.size), dtype=bool) for st in op.result.buses]
        # every other NUMBER field of the bus status (derived from its dataclass), int64 per cycle and bus
        status_cls = type(op.result.buses[0]) if op.result.buses else None
        skip = (*EXCLUDED, "verdict", "wkc")
        self.status_names = (
            tuple(f.name for f in of(status_cls, Carry.NUMBER, exclude=skip)) if status_cls else ()
        )
        self.text_names = tuple(f.name for f in of(status_cls, Carry.TEXT)) if status_cls else ()
        self._status = np.zeros((0, len(self.bus_names), len(self.status_names)), dtype=np.int64)
        self._texts: list[dict[str, list[tuple[int, str | None]]]] = [
            {t: [] for t in self.text_names} for _ in self.bus_names
        ]
        self._last_texts = [[getattr(st, t) for t in self.text_names] for st in op.result.buses]
        self._inputs = {
            k: np.zeros((0, g.image.n_axes), g.image.inputs.values.dtype) for k, g in op.groups.items()
        }
        self._outputs = {
            k: np.zeros((0, g.image.n_axes), g.image.outputs.values.dtype) for k, g in op.groups.items()
        }
        self._events: list[TraceEvent] = []
        self._recoveries = [st.recoveries for st in op.result.buses]

    def _grow(self) -> None:
        cap = self._cap + CHUNK

        def grown(a: npt.NDArray[Any]) -> npt.NDArray[Any]:
            out = _zeros((cap, *a.shape[1:]), a.dtype)
            out[: self.n] = a[: self.n]
            return out

        self._fresh, self._stop = grown(self._fresh), grown(self._stop)
        self._verdict, self._wkc = grown(self._verdict), grown(self._wkc)
        self._status = grown(self._status)
        self._slave_fresh = [grown(a) for a in self._slave_fresh]
        self._inputs = {k: grown(a) for k, a in self._inputs.items()}
        self._outputs = {k: grown(a) for k, a in self._outputs.items()}
        self._cap = cap

    def note_events(self, events: list[Any]) -> None:
        """Keep the cycle's events (whatever ``CycleResult.events`` carries), at the row of this cycle."""
        k = self.n
        self._events.extend(TraceEvent(k, event_kind(e), e) for e in events)

    def close(self) -> None:
        """The network closed: the trace stays readable."""

    def capture(self, result: CycleResult, t0_ns: int = 0) -> None:
        """Keep this cycle (an observer of the network: called at the end of every ``exchange()``)."""
        if self.n == self._cap:
            self._grow()
        k = self.n
        self._fresh[k] = result.fresh
        self._stop[k] = result.safe_stop
        for j, st in enumerate(result.buses):
            self._verdict[k, j] = int(st.verdict)
            self._wkc[k, j] = st.wkc
            self._slave_fresh[j][k] = st.fresh
            row = self._status[k, j]
            for i, name in enumerate(self.status_names):
                v = getattr(st, name)
                row[i] = NO_VALUE if v is None else v
            last = self._last_texts[j]
            for i, name in enumerate(self.text_names):
                v = getattr(st, name)
                if v is not last[i]:  # a new object; a structured one counts when it differs (as recorded)
                    same = not (v is None or isinstance(v, str)) and v == last[i]
                    last[i] = v
                    if not same:
                        self._texts[j][name].append((k, text(v)))
            if st.recoveries != self._recoveries[j]:  # a recovery brought a slave back in this cycle
                self._recoveries[j] = st.recoveries
                self._events.append(TraceEvent(k, "recovered", _Recovered(k, st.name, st.recoveries)))
        for name, g in self._op.groups.items():
            # field by field: a whole-record copy may carry bytes between the fields along
            for dst, src in (
                (self._inputs[name][k], g.image.inputs.values),
                (self._outputs[name][k], g.image.outputs.values),
            ):
                for field in src.dtype.names or ():
                    dst[field] = src[field]
        self.n = k + 1

    # -- reading -----------------------------------------------------------------------------
    def __len__(self) -> int:
        return self.n

    def mark(self) -> int:
        """The index the next cycle will have: ``since=trace.mark()`` before injecting a fault."""
        return self.n

    @property
    def fresh(self) -> npt.NDArray[np.bool_]:
        """Per cycle: every slave of every bus delivered fresh inputs."""
        return self._fresh[: self.n]

    @property
    def safe_stop(self) -> npt.NDArray[np.bool_]:
        """Per cycle: the safe stop was latched after the cycle."""
        return self._stop[: self.n]

    def _bus(self, bus: str) -> int:
        if bus not in self.bus_names:
            raise FieldbusError(f"no bus '{bus}' in this trace (have: {', '.join(self.bus_names)})")
        return self.bus_names.index(bus)

    def verdict(self, bus: str) -> npt.NDArray[np.int8]:
        """Per cycle, bus ``bus``'s verdict (``fieldbus.core.wkc.Verdict``: 0 OK, 1 SHORT, 2 TIMEOUT)."""
        return self._verdict[: self.n, self._bus(bus)]

    def wkc(self, bus: str) -> npt.NDArray[np.int32]:
        """Per cycle, bus ``bus``'s working counter (CAN: frames that came; -1 before the first)."""
        return self._wkc[: self.n, self._bus(bus)]

    def status(self, bus: str, name: str) -> npt.NDArray[np.int64]:
        """Per cycle, the NUMBER field ``name`` of bus ``bus``'s ``BusStatus`` (``ran``, ``recoveries``,
        ``dc_time_ns``, ...: every one but ``verdict`` and ``wkc``, which have their own arrays; a bool as
        0/1, an enum as its value, ``None`` as ``fieldbus.core.status_fields.NO_VALUE``)."""
        if name not in self.status_names:
            raise FieldbusError(
                f"BusStatus has no number field '{name}' kept per cycle (have: {', '.join(self.status_names)})"
            )
        return self._status[: self.n, self._bus(bus), self.status_names.index(name)]

    def texts(self, bus: str, name: str) -> list[tuple[int, str | None]]:
        """The changes of the text field ``name`` of bus ``bus``'s ``BusStatus`` (``recovery_error``,
        ``last_error``, ...: every field that is not a number), as ``(cycle, its str() or None)``."""
        if name not in self.text_names:
            raise FieldbusError(f"BusStatus has no text field '{name}' (have: {', '.join(self.text_names)})")
        return list(self._texts[self._bus(bus)][name])

    def slave_fresh(self, bus: str) -> npt.NDArray[np.bool_]:
        """Per cycle and slave of bus ``bus`` (wire / node order): its inputs were fresh."""
        return self._slave_fresh[self._bus(bus)][: self.n]

    def _group(self, group: str) -> None:
        if group not in self._inputs:
            raise FieldbusError(
                f"no axis group '{group}' in this trace (have: {', '.join(self.group_names)})"
            )

    def inputs(self, group: str) -> npt.NDArray[Any]:
        """Per cycle and axis, group ``group``'s inputs in engineering units (a structured array:
        ``trace.inputs("arm")["position_actual_value"][k, axis]``); a stale cycle's row holds the
        inputs as they were held."""
        self._group(group)
        return self._inputs[group][: self.n]

    def outputs(self, group: str) -> npt.NDArray[Any]:
        """Per cycle and axis, group ``group``'s outputs in engineering units as cycle k's frame sent
        them (row k); the safe outputs of a stop latched in cycle k from row k + 1 on (see the module)."""
        self._group(group)
        return self._outputs[group][: self.n]

    @property
    def events(self) -> list[TraceEvent]:
        """Every event so far, in order (a copy)."""
        return list(self._events)

    def events_of(
        self, kind: str | None = None, *, since: int = 0, until: int | None = None
    ) -> list[TraceEvent]:
        """The events of kind ``kind`` (None: any) in cycles [``since``, ``until``)."""
        end = self.n if until is None else until
        return [e for e in self._events if since <= e.cycle < end and (kind is None or e.kind == kind)]

    def group_fresh(self, group: str) -> npt.NDArray[np.bool_]:
        """Per cycle and axis of group ``group``: that axis's slave delivered fresh inputs."""
        self._group(group)
        return self._slave_fresh[self._group_bus[group]][: self.n][:, self._group_rows[group]]

    def group_bus(self, group: str) -> str:
        """The bus that group ``group`` is on."""
        self._group(group)
        return self.bus_names[self._group_bus[group]]

    def arrays(self) -> dict[str, npt.NDArray[Any]]:
        """Everything kept, by name (``fresh``, ``safe_stop``, ``<bus>.verdict``, ``<group>.inputs``, ...).

        Two runs of a scenario on a virtual clock give equal arrays, bit for bit: inputs and
        outputs come as packed copies (no padding bytes between fields, whose contents numpy
        leaves undefined), so ``a.tobytes() == b.tobytes()`` compares the values themselves.
        """
        from numpy.lib.recfunctions import repack_fields

        out: dict[str, npt.NDArray[Any]] = {"fresh": self.fresh, "safe_stop": self.safe_stop}
        for b in self.bus_names:
            out[f"{b}.verdict"] = self.verdict(b)
            out[f"{b}.wkc"] = self.wkc(b)
            out[f"{b}.slave_fresh"] = self.slave_fresh(b)
            for name in self.status_names:
                out[f"{b}.{name}"] = self.status(b, name)
        for g in self.group_names:
            out[f"{g}.inputs"] = repack_fields(self.inputs(g))
            out[f"{g}.outputs"] = repack_fields(self.outputs(g))
        return out


@dataclass(frozen=True)
class _Recovered:
    """A bus's recovery brought a slave back (``BusStatus.recoveries`` rose to ``recoveries``)."""

    cycle: int
    bus: str
    recoveries: int
    kind: str = "recovered"

    def __str__(self) -> str:
        return f"cycle {self.cycle} bus '{self.bus}': recovered (recoveries {self.recoveries})"
