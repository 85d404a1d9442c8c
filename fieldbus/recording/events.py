"""Events derived from consecutive recorded cycles, in the writer thread (the cycle only copies rows).

Each block is compared with the row before it (the previous block's last row,
kept across blocks; for the first block, the counters as recording began, so
a change inside a dropped block is reported at the first cycle recorded after it): a bus's safe stop latched or cleared, a recovery started
or finished, the recovery counter grown, a new recovery error, new EMCY
messages, a CANopen node's NMT state changed, an axis's CiA 402 state
(decoded from its ``statusword`` input) changed. An event carries the index
and start time of the first cycle in which the new value was seen. Events the
cycle itself notes when they happen (an SDO served in OP that the slave
aborted: :meth:`~fieldbus.recording.ring.Ring.note`) join them in the writer.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from fieldbus.core.cia402 import UNKNOWN_STATE, State402, decode_states
from fieldbus.core.network import row_names
from fieldbus.recording.ring import EMERGENCIES, OWN, TEXTS, Ring, Snapshot

TOGGLES = (
    ("safe_stop", "safe_stop", "safe_stop_cleared"),
    ("recovering", "recovery_started", "recovery_finished"),
)


def state_name(code: int) -> str:
    """A CiA 402 state code (:func:`~fieldbus.core.cia402.decode_states`) as its name."""
    return "UNKNOWN" if code == UNKNOWN_STATE else State402(code).name


@dataclass
class _Group:
    name: str
    bus: str
    axes: tuple[str, ...]
    statusword: bool


class EventDeriver:
    """Turns blocks of a :class:`Ring` into event dicts (see ``schema.EVENT_SCHEMA``)."""

    def __init__(self, ring: Ring) -> None:
        self.ring = ring
        self.buses = [(s.backend.bus.name, tuple(a.slave.name for a in s.backend.areas)) for s in ring.buses]
        self.groups = [
            _Group(
                g.group.name,
                next(s.backend.bus.name for s in ring.buses if g.group in s.backend.groups),
                row_names(g.group.slaves),  # one per image row (each axis of a multi-axis slave)
                "statusword" in (g.group.image.inputs.values.dtype.names or ()),
            )
            for g in ring.groups
        ]
        self._prev: npt.NDArray[np.int64] | None = ring.baseline  # counters as recording began
        self._prev_nmt: list[npt.NDArray[np.int16] | None] = list(ring.baseline_nmt)
        self._prev_states: list[npt.NDArray[np.int8] | None] = [None] * len(ring.groups)

    def block(self, snap: Snapshot, inputs: list[npt.NDArray[Any]]) -> list[dict[str, Any]]:
        """Events of one block; ``inputs``: each group's decoded input values, (rows, axes)."""
        ints = snap.ints
        a = ints if self._prev is None else np.concatenate([self._prev[None, :], ints])
        cycle, t_ns = a[:, OWN.index("cycle")], a[:, OWN.index("t_ns")]
        events: list[dict[str, Any]] = []

        def emit(row: int, kind: str, **more: Any) -> None:
            events.append({"cycle": int(cycle[row]), "t_ns": int(t_ns[row]), "kind": kind, **more})

        for k, (bus, slaves) in enumerate(self.buses):
            slot = self.ring.buses[k]

            def col(name: str, slot_base: int = slot.base) -> npt.NDArray[np.int64]:
                return a[:, slot_base + self.ring.columns.index(name)]

            for field, on, off in TOGGLES:
                x = col(field)
                for i in np.flatnonzero(np.diff(x)):
                    emit(int(i) + 1, on if x[i + 1] else off, bus=bus)
            x = col("recoveries")
            for i in np.flatnonzero(np.diff(x) > 0):
                emit(int(i) + 1, "recovered", bus=bus, old=int(x[i]), new=int(x[i + 1]))
            for t, name in enumerate(self.ring.columns.texts):  # each TEXT field: an event of its name
                x = col(f"{name}_seq")
                for i in np.flatnonzero(np.diff(x)):
                    text = self.ring.texts[k][t][int(x[i + 1]) % TEXTS]
                    if text is not None:
                        emit(int(i) + 1, name, bus=bus, detail=text)
            x = col(EMERGENCIES)
            for i in np.flatnonzero(np.diff(x) > 0):
                new = int(x[i + 1] - x[i])
                emit(
                    int(i) + 1,
                    "emcy",
                    bus=bus,
                    old=int(x[i]),
                    new=int(x[i + 1]),
                    detail=self._emcy(slot, new),
                )
            nmt = snap.nmt[k]
            if nmt is not None:
                prev = self._prev_nmt[k]
                both = nmt if prev is None else np.concatenate([prev[None, :], nmt])
                rows, nodes = np.nonzero(np.diff(both, axis=0))
                for r, j in zip(rows, nodes, strict=True):  # rows of `both` line up with `a`
                    emit(
                        int(r) + 1,
                        "nmt_state",
                        bus=bus,
                        slave=slaves[j],
                        old=int(both[r, j]),
                        new=int(both[r + 1, j]),
                    )
                self._prev_nmt[k] = nmt[-1].copy()
        for k, g in enumerate(self.groups):
            if not g.statusword:
                continue
            states = np.empty(inputs[k].shape, dtype=np.int8)
            decode_states(inputs[k]["statusword"], states)
            prev_s = self._prev_states[k]
            both_s = states if prev_s is None else np.concatenate([prev_s[None, :], states])
            rows, axes = np.nonzero(np.diff(both_s, axis=0))
            for r, j in zip(rows, axes, strict=True):
                emit(
                    int(r) + 1,
                    "cia402_state",
                    bus=g.bus,
                    group=g.name,
                    slave=g.axes[j],
                    old=state_name(int(both_s[r, j])),
                    new=state_name(int(both_s[r + 1, j])),
                )
            self._prev_states[k] = states[-1].copy()
        self._prev = ints[-1].copy()
        events.sort(key=lambda e: e["cycle"])
        return events

    @staticmethod
    def _emcy(slot: Any, new: int) -> str:
        """The newest ``new`` EMCY messages the backend keeps (read now: close to, not exactly, that cycle's)."""
        try:
            items = list(slot.backend.emergencies)[-new:]
        except Exception:  # the backend's list changed meanwhile: the count is still right
            return ""
        return "; ".join(str(e) for e in items)
