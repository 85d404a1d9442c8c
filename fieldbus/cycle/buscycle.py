"""One bus's cycle: encode (the one output path), send, receive, judge, accept and decode; its recovery step.

A :class:`BusCycle` owns one backend, its :class:`~fieldbus.core.safety.SafetyPolicy`
and its :class:`~fieldbus.cycle.status.BusStatus`. Nothing it calls can raise
out of it for a bus fault (S1): what the backend raises becomes the verdict
ERROR with a :class:`~fieldbus.cycle.status.BusFault`. Inputs are copied into
the image only for the slaves the policy calls fresh (S2, S3); every command
value passes the group's :class:`~fieldbus.core.output_rules.OutputRules`
before any codec (S11). The drive-fault watch (CiA 402 statusword bit 3) runs
on the rows accepted; a fault whose code must be read acyclically goes to
``on_drive_fault``.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import numpy.typing as npt

from fieldbus.backends.base import Backend
from fieldbus.core.drivefault import DriveFault, DriveFaultWatch
from fieldbus.core.hold import TransitionHold
from fieldbus.core.output_rules import OutputRules, channel_limits, slave_limits
from fieldbus.core.pdo.image import ProcessImage
from fieldbus.core.pdo.names import STATUSWORD
from fieldbus.core.safety import OK, SafetyPolicy, Verdict
from fieldbus.cycle.status import BusEvent, BusFault, BusStatus, CycleEvent, FaultKind, missed, raised, reason
from fieldbus.platform import phases as ph

MODES_DISPLAY = 0x6061  # CiA 402 modes of operation display: the output path's step rule holds in 8-10

Events = list[CycleEvent]


class BusCycle:
    """The cycle of one bus, which runs every ``every``-th call of the network's cycle (its
    cycle_time_us over the shortest one)."""

    def __init__(self, backend: Backend, policy: SafetyPolicy, every: int = 1) -> None:
        self.backend = b = backend
        self.policy = policy
        self.every = every
        self.status = st = BusStatus(b.bus.name, b.expected_wkc, policy.fresh)
        st.recovering, st.recoveries, st.recovery_error = b.recovering, b.recoveries, b.last_recovery_error
        # the one output path: every group's command values pass the rules before any codec (output_rules)
        self.encoders: list[tuple[OutputRules, ProcessImage]] = []
        self.holds: dict[str, TransitionHold] = {}  # raw-CAN groups: their hold command (fieldbus.core.hold)
        for g in b.groups:
            lay = g.image.layout
            sw, md = lay.inputs.find(STATUSWORD), lay.inputs.find(MODES_DISPLAY)
            rules = OutputRules(
                g.name,
                g.image.outputs,
                channel_limits(g.slaves[0].map, lay.outputs, b.bus.cycle_time_us / 1e6),
                g.image.inputs.values[sw.name] if sw is not None and not sw.channel.scaled else None,
                g.image.inputs.values[md.name] if md is not None and not md.channel.scaled else None,
                slave_limits(g.slaves, lay.outputs, b.bus.cycle_time_us / 1e6),  # the network's narrowing
            )
            self.encoders.append((rules, g.image))
            if g.slaves[0].map.rawcan is not None:  # raw-CAN motors hold after a transition (S12)
                self.holds[g.name] = TransitionHold(g.image, rules)
        self.rules = tuple(r for r, _ in self.encoders)
        # drive faults (CiA 402 statusword bit 3), watched on the rows each cycle accepted
        self.watches: list[tuple[DriveFaultWatch, npt.NDArray[np.bool_]]] = []
        for g in b.groups:
            w = DriveFaultWatch(g.name, g.image, tuple(s.name for s in g.slaves))
            if w.active:
                self.watches.append((w, policy.fresh[g.first : g.first + len(g.slaves)]))
        # a drive fault whose code (0x603F) or history (0x10F3) is to be read acyclically; None: not read
        self.on_drive_fault: Callable[[DriveFault], None] | None = None
        self._bus_off = int(b.bus_off)  # CAN bus-off reports so far (0 elsewhere)
        # the bus can tell per-slave arrival (it overrides Backend.arrived); else the cycle does not ask
        self._arrives = type(b).arrived is not Backend.arrived or "arrived" in vars(b)

    @property
    def name(self) -> str:
        return self.status.name

    def hold_hook(self, i: int) -> None:
        """What the backend calls after it seeded motor ``i``'s outputs (recover, set_mode): its group's
        output rules restart from the seed (:meth:`~fieldbus.core.output_rules.OutputRules.rebase`)."""
        b = self.backend
        a = b.areas[i]
        hold = self.holds.get(b.groups[a.group].name)
        if hold is not None:
            rows = np.zeros(hold.image.n_axes, dtype=bool)
            rows[a.row : a.row + a.axes] = True
            hold.rules.rebase(rows)

    def due(self, cycle: int) -> bool:
        """Start call ``cycle``: whether the bus runs in it (``status.ran``); this cycle's error cleared."""
        st = self.status
        st.ran = cycle % self.every == 0
        st.error = st.fault = None
        return st.ran

    def encode(self, cycle: int, events: Events) -> None:
        """The one output path: each group's outputs pass the rules, then are encoded.

        A refused value (NaN, infinity, out of the map's window, too big a step) is replaced in the image
        before ``to_wire()`` and before a raw-CAN family reads it; its streak's first cycle is an
        :class:`~fieldbus.core.output_rules.OutputClamp` event.
        """
        for rules, image in self.encoders:
            if rules.apply():
                events.extend(rules.events(cycle))
            else:
                rules.settle()
            image.outputs.to_wire()

    def send(self, cycle: int, events: Events, pt: ph.PhaseTimer | None = None) -> None:
        """Encode and send this cycle's outputs; an exception is this bus's SEND_ERROR (never raised)."""
        try:
            self.encode(cycle, events)
            if pt is not None:
                pt.mark(ph.ENCODE)
            self.backend.send()
        except Exception as exc:
            raised(self.status, FaultKind.SEND_ERROR, exc)
        if pt is not None:
            pt.mark(ph.SEND)

    def receive(self, cycle: int, events: Events, pt: ph.PhaseTimer | None = None) -> Verdict:
        """Receive, judge, accept the fresh slaves' inputs and decode them; watch for drive faults.

        Never raises (S1): a receive that raises is a RECEIVE_ERROR, a rise of
        the CAN controller's bus-off reports a BUS_OFF, and either is the verdict
        ERROR. A miss without an error keeps its TIMEOUT / WKC_MISMATCH fault.
        """
        b, policy, st = self.backend, self.policy, self.status
        wkc: int | None = None
        arrived = None
        if st.error is None:
            try:
                wkc = b.receive()
                if self._arrives:
                    arrived = b.arrived()
            except Exception as exc:
                raised(st, FaultKind.RECEIVE_ERROR, exc)
        if pt is not None:
            pt.mark(ph.WAIT)
        off = b.bus_off
        if off != self._bus_off:  # a CAN controller that reported bus-off: a bus error (S1)
            off = int(off)
            if off > self._bus_off and st.error is None:
                st.error = f"bus-off reported by the CAN controller ({off} since bring-up)"
                st.fault = BusFault(st.name, FaultKind.BUS_OFF, st.expected_wkc, wkc, st.error)
            self._bus_off = off
        verdict = policy.judge(wkc, arrived, st.error)
        st.verdict = verdict
        st.wkc = policy.last_wkc
        st.consecutive_misses = policy.consecutive_misses
        st.safe_stop = policy.safe_stop
        st.release_pending = policy.clear_requested
        st.dc_time_ns = b.dc_time_ns
        st.dc_sync_error_ns = b.dc_sync_error_ns
        if verdict is not OK:
            if st.fault is None:
                st.fault = missed(st, verdict, policy.last_wkc)
            st.last_fault = st.fault
        if st.error is not None:
            st.errors += 1
            st.last_error = st.error
            events.append(BusEvent(cycle, st.name, "bus_error", st.error))
        if policy.latched_now:
            events.append(BusEvent(cycle, st.name, "safe_stop", f"{policy.consecutive_misses} misses"))
        if policy.released_now:
            events.append(BusEvent(cycle, st.name, "released"))
        if pt is not None:
            pt.mark(ph.JUDGE)
        if verdict is OK or (arrived is not None and policy.fresh.any()):
            b.accept_inputs(policy.fresh, verdict is OK)  # stale rows keep their last accepted bytes (S2)
            for watch, rows in self.watches:
                for fault in watch.step(rows, cycle):
                    events.append(fault)
                    drive = b.areas[b.slave_index(fault.slave)].slave.map
                    if self.on_drive_fault is not None and (
                        fault.code is None or drive.ethercat.diagnosis_history
                    ):
                        self.on_drive_fault(fault)
        return verdict

    def recover(self) -> None:
        """One bounded recovery step after a miss and while the backend recovers (its only caller), and the
        recovery's status copied. The network skips it on a clean cycle (fresh, no error, not recovering):
        no step is due then, and recoveries and their errors change only in a step."""
        b, st = self.backend, self.status
        if st.error is None and (st.verdict is not OK or b.recovering):
            try:
                b.recover_step()
            except Exception as exc:  # recover_step never raises by contract; a backend bug is a miss reason
                st.last_error = reason(exc)
        st.recovering = b.recovering
        st.recoveries = b.recoveries
        st.recovery_error = b.last_recovery_error

    def settle_answered(self, unheard: npt.NDArray[np.bool_]) -> None:
        """After a wind-down cycle: mark in ``unheard`` the slaves heard not to answer (S6).

        A short reply is judged per slave: the slaves the backend can tell answered
        (``Backend.slaves_answered``) are fresh and their inputs accepted; a bus with
        no reply (timeout, error) leaves every slave unheard.
        """
        b, policy, st = self.backend, self.policy, self.status
        unheard.fill(st.verdict in (Verdict.TIMEOUT, Verdict.ERROR))  # no reply: nobody heard
        if st.verdict is not Verdict.SHORT:
            return
        try:
            answered = b.slaves_answered(policy.last_wkc)
        except Exception:  # a backend bug: nothing attributed
            answered = None
        if answered is None:
            return  # a short reply nobody can attribute: every slave stale, none given up
        np.logical_not(answered, out=unheard)
        if not np.array_equal(answered, policy.fresh):
            np.copyto(policy.fresh, answered)
            b.accept_inputs(policy.fresh)  # only the slaves that answered (S2 for the others)
