"""Acyclic access in OP: the SDO queue served by the cycle, the drive-fault follow-up reads, ESC diagnostics.

Any thread submits an SDO transfer and gets a future (checked at the door, S5:
a malformed request raises there and nothing is queued); the cycle serves one
transfer per bus at a time, one bounded step per cycle, never while the bus
is recovering (:meth:`AcyclicService.step`). A transfer that fails in the
cycle fails its future only, with its cause (S5). A transfer the slave
aborted is an :class:`~fieldbus.cycle.status.SdoAbortEvent` among the cycle's
events (a recording writes it). A drive fault whose code is not in a PDO gets
its 0x603F read (and 0x10F3, the diagnosis history, when its map says it keeps
one) through the same queue; while that read is pending the axis's reset is
held (:meth:`AcyclicService.code_pending`).
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Sequence
from concurrent.futures import CancelledError, Future, wait
from dataclasses import replace

import numpy as np
import numpy.typing as npt

from fieldbus.backends.base import AxisGroup, Backend, SdoRequest
from fieldbus.core.drivefault import DriveFault, FaultFollowUp
from fieldbus.core.esc_errors import describe_change
from fieldbus.cycle.status import BusEvent, BusStatus, CycleEvent, SdoAbortEvent, reason
from fieldbus.errors import (
    BusTimeoutError,
    FieldbusError,
    PhaseError,
    RequestError,
    SdoAbortError,
    abort_name,
)

MAX_SDO_BYTES = 1 << 20  # the largest SDO download accepted at submit, bytes

Events = list[CycleEvent]


class AcyclicService:
    """SDO transfers and diagnostics of every bus of a network in OP, served by the cycle's thread."""

    def __init__(self, backends: Sequence[Backend], groups: dict[str, AxisGroup]) -> None:
        self.backends = list(backends)
        self._group_bus = {g.name: b.bus.name for b in self.backends for g in b.groups}
        # SDO transfers asked for while the cycle runs (any thread), served by the cycle, one per bus at a time
        self.pending: list[deque[SdoRequest]] = [deque() for _ in self.backends]
        self.current: list[SdoRequest | None] = [None] * len(self.backends)
        self.cycle_thread: int | None = None  # the thread that runs the cycle (set by its first call)
        self.follow_ups: list[FaultFollowUp] = []  # 0x603F read when not in a PDO, 0x10F3 when kept
        # per group and row: its fault's 0x603F read is not served yet (a reset now would clear the code)
        self._code_pending: dict[str, npt.NDArray[np.bool_]] = {
            name: np.zeros(g.image.n_axes, dtype=bool) for name, g in groups.items()
        }

    # -- any thread ------------------------------------------------------------------------
    def submit(
        self, k: int, slave: str, index: int, sub_index: int, data: bytes | None
    ) -> Future[bytes | None]:
        """Queue a transfer on bus ``k``; the request is checked here (S5): a malformed one raises
        :class:`RequestError` (or :class:`FieldbusError` for an unknown slave) and nothing is queued."""
        b = self.backends[k]
        for what, value, top in (("index", index, 0xFFFF), ("sub_index", sub_index, 0xFF)):
            if not isinstance(value, int) or isinstance(value, bool) or not 0 <= value <= top:
                shown = (
                    f"0x{value:X}" if isinstance(value, int) and not isinstance(value, bool) else repr(value)
                )
                raise RequestError(
                    f"SDO {what} {shown} out of range 0..0x{top:X} (bus '{b.bus.name}' slave '{slave}')"
                )
        if data is not None and not 1 <= len(data) <= MAX_SDO_BYTES:
            raise RequestError(
                f"SDO download to 0x{index:04X}:{sub_index:02X} of '{slave}': {len(data)} bytes "
                f"(1..{MAX_SDO_BYTES} accepted)"
            )
        req = SdoRequest(b.slave_index(slave), index, sub_index, data)
        self.pending[k].append(req)
        return req.future

    def wait(self, future: Future[bytes | None], timeout_s: float) -> bytes | None:
        """Wait for ``future`` from a thread other than the cycle's; withdraw it when not served in time."""
        if threading.get_ident() == self.cycle_thread:
            future.cancel()
            raise FieldbusError(
                "sdo_read/sdo_write in OP wait for the cycle, and this thread runs the cycle: call them from "
                "another thread, or use submit_sdo_read/submit_sdo_write and look at the future in later cycles"
            )
        # wait() reports done or not without raising, so the transfer's own BusTimeoutError (a
        # TimeoutError, as the future's timeout is) cannot be taken for "not served"
        if not wait((future,), timeout_s).done and future.cancel():
            # withdrawn: it cannot run after the caller was told it failed (a write applied late)
            raise BusTimeoutError(
                f"SDO transfer not served within {timeout_s:g} s (withdrawn): is exchange() being called?"
            )
        if not wait((future,), timeout_s).done:  # the cycle took it up meanwhile: as long again
            raise BusTimeoutError(
                f"SDO transfer started but not finished within {2 * timeout_s:g} s: it may still be applied"
            )
        return future.result()

    def code_pending(self, group: str) -> npt.NDArray[np.bool_]:
        """Per row of ``group``: its fault's 0x603F read is not served yet (the same array every cycle)."""
        return self._code_pending[group]

    # -- the cycle's thread ------------------------------------------------------------------
    def step(self, k: int, st: BusStatus, cycle: int, events: Events) -> None:
        """Bus ``k``'s acyclic step in this cycle, after its recovery step: one bounded SDO step, then one
        diagnostic read (EtherCAT ESC counters), both only while it is not recovering. Never raises."""
        if st.recovering:
            return
        b = self.backends[k]
        if self.current[k] is not None or self.pending[k]:
            try:
                self._serve(k, b, cycle, events)
            except Exception as exc:  # fails that transfer only, with its cause (S5)
                req = self.current[k]
                self.current[k] = None
                text = reason(exc)
                if req is not None:
                    req.finish(error=FieldbusError(f"SDO transfer failed in the cycle: {text}"))
                st.last_error = text
                events.append(BusEvent(cycle, st.name, "acyclic_error", text))
        if b.error_watch is None:
            return  # nothing watched: no diagnostic read (Backend.diag_step)
        try:
            changes = b.diag_step()  # one diagnostic datagram at most, in a cycle nothing else used
        except Exception as exc:  # diag_step never raises by contract; a backend bug is a reason
            changes, st.last_error = [], reason(exc)
        if changes:
            names = [a.slave.name for a in b.areas]
            events.extend(BusEvent(cycle, st.name, *describe_change(c, names)) for c in changes)

    def _serve(self, k: int, b: Backend, cycle: int, events: Events) -> None:
        req = self.current[k]
        if req is None:
            req = self.current[k] = self.pending[k].popleft()
            if not req.future.set_running_or_notify_cancel():
                self.current[k] = None
                return
        if b.acyclic_step(req):
            self.current[k] = None
            exc = req.future.exception(0) if req.future.done() else None
            if isinstance(exc, SdoAbortError):  # the slave aborted it: an event (a recording keeps it)
                events.append(
                    SdoAbortEvent(
                        cycle,
                        b.bus.name,
                        "sdo_abort",
                        str(exc),
                        slave=b.areas[req.slave].slave.name,
                        access="read" if req.data is None else "write",
                        index=req.index,
                        sub_index=req.sub_index,
                        code=exc.code,
                        name=abort_name(exc.code),
                    )
                )

    def fail_pending(self) -> None:
        """The network leaves OP: every transfer not finished fails with :class:`PhaseError`."""
        for k, pending in enumerate(self.pending):
            cur = self.current[k]
            if cur is not None:
                cur.finish(error=PhaseError("the network left OP before this SDO transfer finished"))
                self.current[k] = None
            while pending:
                req = pending.popleft()
                if req.future.set_running_or_notify_cancel():
                    req.finish(error=PhaseError("the network left OP before this SDO transfer was served"))

    # -- drive-fault follow-up reads ------------------------------------------------------------
    def read_code(self, k: int, fault: DriveFault) -> None:
        """Ask for 0x603F of a faulted drive whose map does not have it in a PDO, and for its diagnosis
        history 0x10F3 when its map says it keeps one (served by the cycle, one upload at a time)."""
        b = self.backends[k]
        slave = b.slave_index(fault.slave)
        drive = b.areas[slave].slave.map
        pending = self.pending[k]

        def submit(index: int, sub_index: int) -> Future[bytes | None]:
            req = SdoRequest(slave, index, sub_index, None)
            pending.append(req)
            return req.future

        code = drive.axis_index(0x603F, fault.slave_axis) if fault.code is None else None
        if code is not None and fault.group in self._code_pending:
            self._code_pending[fault.group][fault.axis] = True
        self.follow_ups.append(
            FaultFollowUp(fault, submit, code_index=code, history=drive.ethercat.diagnosis_history)
        )

    def collect(self, cycle: int, events: Events) -> None:
        """Drive faults whose follow-up reads finished: the fault again, with its code (and history), as an event."""
        keep = []
        for follow in self.follow_ups:
            try:
                done = follow.poll()
            except Exception as exc:  # never silent: the fault stays reported without its code, and why
                why = "cancelled" if isinstance(exc, CancelledError) else reason(exc)
                fault = follow.fault
                self._release_reset(fault)
                events.append(
                    BusEvent(
                        cycle,
                        self._group_bus[fault.group],
                        "acyclic_error",
                        f"0x603F of {fault.slave}: {why}",
                    )
                )
                continue
            if not follow.code_pending:
                self._release_reset(follow.fault)
            if done is None:
                keep.append(follow)
                continue
            events.append(replace(done, cycle=cycle))
            if follow.error is not None:
                events.append(BusEvent(cycle, self._group_bus[done.group], "acyclic_error", follow.error))
        self.follow_ups = keep
        for follow in keep:  # a second fault of an axis whose first read just ended: still pending
            pending = self._code_pending.get(follow.fault.group)
            if pending is not None and follow.code_pending:
                pending[follow.fault.axis] = True

    def _release_reset(self, fault: DriveFault) -> None:
        """The 0x603F read of ``fault`` is over (served or failed): its axis may be reset."""
        pending = self._code_pending.get(fault.group)
        if pending is not None:
            pending[fault.axis] = False
