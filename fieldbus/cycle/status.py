"""What a cycle reports: per-bus status, structured faults, events, the result of one ``exchange()``.

:class:`BusStatus` (one bus in one cycle, updated in place), :class:`BusFault`
(a miss with its structure kept), :class:`BusEvent` (something a bus did),
:class:`CycleResult` (what :meth:`fieldbus.Operational.exchange` returns),
:class:`BusView` (a running bus as an observer sees it) and the
:class:`CycleObserver` protocol. Re-exported by :mod:`fieldbus.network`.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
import numpy.typing as npt

from fieldbus.backends.base import Backend
from fieldbus.core.drivefault import DriveFault
from fieldbus.core.output_rules import OutputClamp, OutputRules
from fieldbus.core.safety import SafetyPolicy, Verdict


@dataclass(frozen=True)
class BusEvent:
    """Something a bus did in one cycle: ``safe_stop`` latched, ``released``, ``bus_error``, ``acyclic_error``."""

    cycle: int
    bus: str
    kind: str
    detail: str = ""

    def __str__(self) -> str:
        return f"cycle {self.cycle} bus '{self.bus}': {self.kind}" + (
            f" ({self.detail})" if self.detail else ""
        )


@dataclass(frozen=True)
class SdoAbortEvent(BusEvent):
    """An SDO transfer served in OP that the slave aborted (``kind`` "sdo_abort", ``detail`` the error's text):
    which slave and object, read or write, the abort code (CiA 301 / ETG.1000.6) and its name."""

    slave: str = ""
    access: str = "read"  # "read" (upload) or "write" (download)
    index: int = 0
    sub_index: int = 0
    code: int = 0
    name: str = ""


CycleEvent = BusEvent | DriveFault | OutputClamp  # what CycleResult.events holds


class CycleObserver(Protocol):
    """What :meth:`Operational.add_observer` takes: a recording, a monitor, a test's probe.

    ``capture`` runs in the cycle's thread at the end of every ``exchange()``
    (keep it short and allocation-free); ``note_events`` gets the cycle's
    events when there are any, before ``capture``; ``close`` runs when the
    network closes.
    """

    def capture(self, res: CycleResult, t0_ns: int) -> None: ...

    def note_events(self, events: list[CycleEvent]) -> None: ...

    def close(self) -> None: ...


@dataclass(frozen=True)
class BusView:
    """One bus as an observer sees it (:attr:`Operational.buses`): its status, statistics and counters.

    The public face of a running bus for monitors, reports and recordings; it
    reads the backend's counters on demand, never in the cycle.
    """

    backend: Backend
    policy: SafetyPolicy
    status: BusStatus
    rules: tuple[OutputRules, ...] = ()  # the output path's rules of its groups (S11)

    @property
    def name(self) -> str:
        return self.backend.bus.name

    @property
    def kind(self) -> str:
        return self.backend.kind

    @property
    def slaves(self) -> tuple[str, ...]:
        return tuple(a.slave.name for a in self.backend.areas)

    def counters(self) -> dict[str, int]:
        """Faults the bus absorbed since bring-up: late replies, stale and extra frames, transmit errors,
        bus-off events, emergencies (0 where the bus has no such thing), the policy's misses and errors,
        and the command values the output path refused (``output_clamps``).
        """
        out = self.backend.counters()
        st = self.policy.stats
        out.update(misses=st.misses, timeouts=st.timeouts, short=st.short, errors=st.errors)
        out.update(safe_stops=st.safe_stops, releases=st.releases, recoveries=self.backend.recoveries)
        out["output_clamps"] = sum(int(r.counts.sum()) for r in self.rules)  # command values refused (S11)
        return out

    def slave_state(self, i: int) -> str:
        """Slave ``i``'s state: ``OP`` when its EtherCAT process data were fresh this cycle (a full
        working counter proves every slave processed the LRW in OP), else what the backend last read."""
        if self.backend.pdo_align == 1 and self.policy.fresh[i]:
            return "OP"
        return self.backend.slave_state(i)


def type_name(exc: BaseException) -> str:
    """An exception's type as kept in a reason: bare for builtins, else prefixed by its top package."""
    t = type(exc)
    return t.__name__ if t.__module__ == "builtins" else f"{t.__module__.split('.')[0]}.{t.__name__}"


def reason(exc: BaseException) -> str:
    """An exception as a reason kept in BusStatus: its type and text."""
    name = type_name(exc)
    text = str(exc)
    return f"{name}: {text}" if text else name


class FaultKind(enum.Enum):
    """What went wrong on a bus in one cycle (the verdict it gave in brackets)."""

    TIMEOUT = "timeout"  # no reply within the receive timeout (TIMEOUT)
    WKC_MISMATCH = (
        "wkc_mismatch"  # a reply, but its working counter (CAN: frames) or arrivals fell short (SHORT)
    )
    BUS_OFF = "bus_off"  # the CAN controller reported bus-off (ERROR)
    SEND_ERROR = "send_error"  # encoding or sending the outputs raised (ERROR)
    RECEIVE_ERROR = "receive_error"  # receiving the replies raised (ERROR)


@dataclass(frozen=True)
class BusFault:
    """A bus's fault in one cycle, with its structure kept (:attr:`BusStatus.fault`).

    ``expected``: the working counter a complete cycle returns (CAN: frames);
    ``received``: what came (None: nothing, or the bus raised); ``text``: the
    reason as :attr:`BusStatus.error` gives it for an error, a description
    otherwise; ``exception``: the type of what the bus raised (None: nothing raised).
    """

    bus: str
    kind: FaultKind
    expected: int
    received: int | None = None
    text: str = ""
    exception: str | None = None

    def __str__(self) -> str:
        """One line, as recordings and /diagnostics show it: ``bus: kind (expected E, received R): text``."""
        got = "nothing" if self.received is None else str(self.received)
        text = f": {self.text}" if self.text else ""
        return f"{self.bus}: {self.kind.value} (expected {self.expected}, received {got}){text}"


def raised(st: BusStatus, kind: FaultKind, exc: BaseException) -> None:
    """The bus raised in this cycle: its reason into ``st.error`` and its fault into ``st.fault``."""
    st.error = reason(exc)
    st.fault = BusFault(st.name, kind, st.expected_wkc, None, st.error, type_name(exc))


def missed(st: BusStatus, verdict: Verdict, received: int) -> BusFault:
    """The fault of a miss without an error (a timeout, a short reply); the last one again if it is the
    same (a long outage allocates nothing per cycle)."""
    kind = FaultKind.TIMEOUT if verdict is Verdict.TIMEOUT else FaultKind.WKC_MISMATCH
    got = None if kind is FaultKind.TIMEOUT else received
    last = st.last_fault
    if last is not None and last.kind is kind and last.received == got:
        return last
    text = (
        "no reply within the receive timeout"
        if got is None
        else f"working counter {got}, expected {st.expected_wkc}"
        if got != st.expected_wkc
        else "not every slave answered"
    )
    return BusFault(st.name, kind, st.expected_wkc, got, text)


@dataclass
class BusStatus:
    """One bus in one cycle (updated in place each cycle)."""

    name: str
    expected_wkc: int
    fresh: npt.NDArray[np.bool_]  # per slave, True: inputs decoded this cycle
    verdict: Verdict = Verdict.OK
    wkc: int = -1
    consecutive_misses: int = 0
    safe_stop: bool = False
    dc_time_ns: int | None = None  # DC system time of this cycle's frame (EtherCAT with DC), ns
    dc_sync_error_ns: int | None = None  # host phase error against the DC cycle, ns
    ran: bool = True  # the bus exchanged this cycle (a bus with a longer cycle_time_us skips cycles)
    recovering: bool = False  # a slave is being brought back to OP
    recoveries: int = 0  # slaves / passes brought back to OP since bring-up
    recovery_error: str | None = None  # the last failed recovery attempt, if any
    error: str | None = None  # this cycle: the exception the bus raised (type: text); None: none
    fault: BusFault | None = None  # this cycle's fault, structured (every miss has one); None: fresh
    last_fault: BusFault | None = None  # the newest fault, kept after the bus is back
    errors: int = 0  # cycles whose bus raised since bring-up (each one a miss that latches the safe stop)
    last_error: str | None = None  # the newest bus error, kept after the bus is back
    release_pending: bool = False  # clear_safe_stop() was asked; the latch opens after enough fresh cycles


@dataclass
class CycleResult:
    """What :meth:`Operational.exchange` returns; the same object, updated every cycle."""

    buses: tuple[BusStatus, ...]
    cycle: int = 0
    fresh: bool = False  # every slave of every bus fresh
    safe_stop: bool = False  # any bus escalated to a safe stop (latched)
    exchange_ns: int = 0  # time spent in exchange(), ns
    events: list[CycleEvent] = field(default_factory=list)  # what happened in this cycle (new list each)
    drive_faults: dict[str, npt.NDArray[np.int64]] = field(
        default_factory=dict
    )  # per group, fault edges per axis
    _by_name: dict[str, BusStatus] = field(default_factory=dict, repr=False)

    def bus(self, name: str) -> BusStatus:
        return self._by_name[name]
