"""When a CANopen node's inputs stop being current: a deadline for every TPDO, liveness for every node.

Each TPDO (node -> master) gets its deadline from its communication
parameters (0x1800 + n, CiA 301 7.2.2 and 7.5.2.35):

- transmission type 1: at every SYNC, so every cycle (the cycle waits for it);
- types 2-240: at every n-th SYNC, so within n cycles;
- types 254/255 (event driven) with an event timer (sub-index 5, ms): at
  least once per event timer;
- anything else (type 0, 252/253, event driven without a timer): none. Such a
  TPDO sends only when its data change, so a value that stays is current
  while the node is alive; the node's liveness must then come from elsewhere.

A node is watched when it has a producer heartbeat (``heartbeat_ms``, checked
by the master's heartbeat consumer) or at least one TPDO with a deadline. A
node that is neither could die unnoticed: :func:`unwatched_reason` says why,
and the network file is refused (:mod:`fieldbus.core.network`).
"""

from __future__ import annotations

from dataclasses import dataclass

from fieldbus.core.pdo.model import DriveMap, Pdo

EVERY_SYNC = 1
SYNC_TYPES = range(1, 241)  # synchronous, cyclic: every n-th SYNC
EVENT_TYPES = (254, 255)  # event driven (manufacturer / device profile specific)


@dataclass(frozen=True)
class TpdoDeadline:
    """How often a TPDO must come: every ``syncs`` SYNCs, or every ``event_ms`` ms; both 0: no deadline."""

    syncs: int = 0
    event_ms: int = 0

    @property
    def every_sync(self) -> bool:
        return self.syncs == EVERY_SYNC

    @property
    def any(self) -> bool:
        return self.syncs > 0 or self.event_ms > 0


def tpdo_deadline(pdo: Pdo) -> TpdoDeadline:
    """The deadline of TPDO ``pdo`` from its CANopen communication parameters."""
    com = pdo.canopen
    if com is None:
        return TpdoDeadline()
    if com.transmission_type in SYNC_TYPES:
        return TpdoDeadline(syncs=com.transmission_type)
    if com.transmission_type in EVENT_TYPES and com.event_timer > 0:
        return TpdoDeadline(event_ms=com.event_timer)
    return TpdoDeadline()


def unwatched_reason(drive: DriveMap, heartbeat_ms: float) -> str | None:
    """Why a node with map ``drive`` could die unnoticed, with the fix; None when it cannot.

    ``heartbeat_ms``: the node's heartbeat that the master checks (0: none).
    """
    if heartbeat_ms > 0 or any(tpdo_deadline(p).any for p in drive.tpdo):
        return None
    if not drive.tpdo:
        return (
            "a silent node would go unnoticed: it has no TPDO and no heartbeat (heartbeat_ms is 0); "
            "set canopen.heartbeat_ms (e.g. 100)"
        )
    why = ", ".join(f"0x{p.index:04X} {_no_deadline(p)}" for p in drive.tpdo)
    return (
        f"a silent node would go unnoticed: no TPDO has a deadline ({why}) and there is no heartbeat "
        "(heartbeat_ms is 0); set event_timer (ms) on an event-driven TPDO under canopen.pdo, "
        "or canopen.heartbeat_ms (e.g. 100)"
    )


def _no_deadline(pdo: Pdo) -> str:
    t = pdo.canopen.transmission_type if pdo.canopen is not None else None
    if t in EVENT_TYPES:
        return f"is event driven (transmission type {t}) without an event_timer"
    return f"has transmission type {t}, sent only on change or request"
