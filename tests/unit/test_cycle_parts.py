"""Each part of the cycle (fieldbus.cycle) driven alone, without a Network: a scripted backend (a Backend
subclass whose receive returns what the test says, the same bytes in every slave's row) stands for the bus.

These check the parts against the contract in docs/safety.md (S1 verdict not exception, S2 stale rows
untouched, S4 latch, S5 request at the door, S6 wind-down); the end-to-end checks with real frames are the
integration tests (test_safety_contract.py, test_network_safety.py, test_wind_down.py).
"""

from __future__ import annotations

import json
import threading
from collections import deque
from pathlib import Path
from typing import Any

import pytest

from fieldbus.backends.base import Backend
from fieldbus.commands.demo import DEMO_MAP
from fieldbus.core.drivefault import DriveFault
from fieldbus.core.network import load_network
from fieldbus.core.safety import PolicyConfig, SafeStopClearError, SafetyPolicy, Verdict
from fieldbus.cycle.acyclic import AcyclicService
from fieldbus.cycle.buscycle import BusCycle
from fieldbus.cycle.motor_events import MotorEventPump
from fieldbus.cycle.status import BusEvent, CycleEvent, CycleResult, FaultKind, SdoAbortEvent
from fieldbus.cycle.stopping import CLOSE_CYCLES, SafeStopController
from fieldbus.errors import FieldbusError, PhaseError, RequestError, SdoAbortError


class Scripted(Backend):
    """A bus whose replies are a script: an int (working counter, every row filled with ``fill``),
    None (timeout) or an exception (raised by receive)."""

    kind = "scripted"

    def __init__(self, bus: Any) -> None:
        super().__init__(bus)
        self.script: deque[int | BaseException | None] = deque()
        self.fill = 0
        self.recover_calls = 0
        self.sdo: dict[tuple[int, int, int], bytes | BaseException] = {}
        self.recovering_now = False
        self.motor: list[DriveFault] = []

    def open(self) -> None: ...
    def configure(self) -> None: ...
    def safe_op(self) -> None: ...
    def op(self) -> None: ...
    def stop(self) -> None: ...
    def close(self) -> None: ...
    def send(self) -> None: ...

    def receive(self) -> int | None:
        step = self.script.popleft() if self.script else self.expected_wkc
        if isinstance(step, BaseException):
            raise step
        for i in range(self.n_slaves):
            self.in_row(i)[:] = self.fill
        return step

    def recover_step(self) -> bool:
        self.recover_calls += 1
        return True

    @property
    def recovering(self) -> bool:
        return self.recovering_now

    def sdo_read(self, slave: int, index: int, sub_index: int) -> bytes:
        got = self.sdo[(slave, index, sub_index)]
        if isinstance(got, BaseException):
            raise got
        return got

    def take_motor_events(self, cycle: int) -> tuple[DriveFault, ...]:
        out, self.motor = tuple(self.motor), []
        return out


@pytest.fixture
def backend(tmp_path: Path) -> Scripted:
    f = tmp_path / "net.yaml"
    f.write_text(
        "cycle_time_us: 1000\nsafe_stop_after: 3\nbuses:\n"
        f"  - {{name: arm, type: ethercat, interface: x, slaves: [{{name: 'j{{i}}', map: {json.dumps(str(DEMO_MAP))}, count: 2}}]}}\n"
    )
    return Scripted(load_network(f).buses[0])


def _cycle(b: Scripted) -> BusCycle:
    return BusCycle(b, SafetyPolicy(b.expected_wkc, b.n_slaves, PolicyConfig(3, 2), name=b.bus.name))


def _run(bc: BusCycle, cycle: int = 0) -> tuple[Verdict, list[CycleEvent]]:
    events: list[CycleEvent] = []
    assert bc.due(cycle)
    bc.send(cycle, events)
    verdict = bc.receive(cycle, events)
    bc.recover()
    return verdict, events


# -- BusCycle ---------------------------------------------------------------------------------------


def test_bus_cycle_accepts_a_full_reply_and_leaves_stale_rows_untouched(backend: Scripted) -> None:
    bc = _cycle(backend)
    backend.fill = 7
    assert _run(bc)[0] is Verdict.OK and bc.status.fault is None
    wire = backend.groups[0].image.inputs.wire
    assert (wire == 7).all()
    backend.fill, backend.script = 9, deque([backend.expected_wkc - 1])  # a short reply with other bytes
    verdict, _ = _run(bc, 1)
    assert verdict is Verdict.SHORT and (wire == 7).all()  # S2: not a bit changed
    assert bc.status.fault is not None and bc.status.fault.kind is FaultKind.WKC_MISMATCH
    assert backend.recover_calls == 1  # a miss: one recovery step


def test_bus_cycle_turns_a_raising_receive_into_an_error_verdict_and_latches(backend: Scripted) -> None:
    bc = _cycle(backend)
    backend.script = deque([OSError("link down")])
    verdict, events = _run(bc)  # does not raise (S1)
    st = bc.status
    assert verdict is Verdict.ERROR and st.error == "OSError: link down" and st.safe_stop
    assert st.fault is not None and (st.fault.kind, st.fault.exception) == (
        FaultKind.RECEIVE_ERROR,
        "OSError",
    )
    assert [e.kind for e in events if isinstance(e, BusEvent)] == ["bus_error", "safe_stop"]
    assert backend.recover_calls == 0  # an error: no recovery step in that cycle


def test_bus_cycle_makes_a_rise_of_bus_off_a_bus_off_error(backend: Scripted) -> None:
    bc = _cycle(backend)
    backend.bus_off = 1
    verdict, _ = _run(bc)
    assert verdict is Verdict.ERROR and bc.status.fault is not None
    assert bc.status.fault.kind is FaultKind.BUS_OFF and "bus-off" in (bc.status.error or "")
    assert _run(bc, 1)[0] is Verdict.OK  # no new report: fresh again


def test_bus_cycle_runs_every_nth_call(backend: Scripted) -> None:
    bc = BusCycle(backend, SafetyPolicy(backend.expected_wkc, backend.n_slaves), every=3)
    assert [bc.due(c) for c in range(6)] == [True, False, False, True, False, False]


# -- AcyclicService --------------------------------------------------------------------------------


def test_acyclic_checks_at_the_door_and_serves_one_step_per_cycle(backend: Scripted) -> None:
    svc = AcyclicService([backend], {g.name: g for g in backend.groups})
    with pytest.raises(RequestError):
        svc.submit(0, "j0", 0x10000, 0, None)
    with pytest.raises(FieldbusError):
        svc.submit(0, "nobody", 0x6041, 0, None)
    assert not svc.pending[0]  # nothing was queued
    backend.sdo[(1, 0x6041, 0)] = b"\x37\x02"
    a = svc.submit(0, "j1", 0x6041, 0, None)
    b = svc.submit(0, "j1", 0x6041, 0, None)
    st = _cycle(backend).status
    svc.step(0, st, 0, [])
    assert a.result(0) == b"\x37\x02" and not b.done()  # one transfer per cycle
    st.recovering = True
    svc.step(0, st, 1, [])
    assert not b.done()  # never while recovering
    st.recovering = False
    svc.step(0, st, 2, [])
    assert b.result(0) == b"\x37\x02"


def test_acyclic_makes_an_abort_a_typed_event(backend: Scripted) -> None:
    svc = AcyclicService([backend], {g.name: g for g in backend.groups})
    backend.sdo[(0, 0x2000, 1)] = SdoAbortError(0x06020000, index=0x2000, sub_index=1, slave="j0")
    fut = svc.submit(0, "j0", 0x2000, 1, None)
    events: list[CycleEvent] = []
    svc.step(0, _cycle(backend).status, 5, events)
    assert isinstance(fut.exception(0), SdoAbortError)
    (ev,) = events
    assert isinstance(ev, SdoAbortEvent)
    assert (ev.cycle, ev.bus, ev.kind, ev.slave, ev.access, ev.index, ev.sub_index, ev.code) == (
        5,
        "arm",
        "sdo_abort",
        "j0",
        "read",
        0x2000,
        1,
        0x06020000,
    )
    assert ev.name and ev.detail


def test_acyclic_fails_what_is_left_when_op_ends_and_refuses_a_wait_from_the_cycle(backend: Scripted) -> None:
    svc = AcyclicService([backend], {g.name: g for g in backend.groups})
    fut = svc.submit(0, "j0", 0x6041, 0, None)
    svc.cycle_thread = threading.get_ident()
    with pytest.raises(FieldbusError, match="this thread runs the cycle"):
        svc.wait(svc.submit(0, "j0", 0x6041, 0, None), 1.0)
    svc.fail_pending()
    assert isinstance(fut.exception(0), PhaseError)


def test_acyclic_follow_up_holds_the_reset_until_the_code_is_read(backend: Scripted) -> None:
    group = backend.groups[0].name
    svc = AcyclicService([backend], {g.name: g for g in backend.groups})
    slave = backend.slave_index("j1")
    index = backend.areas[slave].slave.map.axis_index(0x603F, 0)
    if index is None:
        pytest.skip("the demo map carries 0x603F in a PDO: no follow-up read")  # pragma: no cover
    backend.sdo[(slave, index, 0)] = (0x2310).to_bytes(2, "little")
    svc.read_code(0, DriveFault(3, group, 1, "j1", None))
    assert svc.code_pending(group).tolist() == [False, True]
    events: list[CycleEvent] = []
    svc.step(0, _cycle(backend).status, 4, events)
    svc.collect(4, events)
    (fault,) = [e for e in events if isinstance(e, DriveFault)]
    assert fault.code == 0x2310 and fault.cycle == 4
    assert svc.code_pending(group).tolist() == [False, False]


# -- SafeStopController ----------------------------------------------------------------------------


def _controller(backend: Scripted) -> tuple[SafeStopController, BusCycle, CycleResult]:
    bc = _cycle(backend)
    res = CycleResult((bc.status,), _by_name={bc.status.name: bc.status})
    return SafeStopController({g.name: g for g in backend.groups}, [bc], res), bc, res


def test_safe_stop_writes_only_while_latched_and_refuses_a_clear_during_an_outage(backend: Scripted) -> None:
    ctl, bc, res = _controller(backend)
    out = backend.groups[0].image.outputs
    out["controlword"][:] = 0x0F
    ctl.before_cycle()
    assert out["controlword"].tolist() == [0x0F, 0x0F]  # not latched: the controller's values stay
    backend.script = deque([None, None, None])
    for c in range(3):
        _run(bc, c)
    assert ctl.after_cycle(bc.policy.safe_stop) is True  # latched now: the writers apply at once
    assert ctl.after_cycle(bc.policy.safe_stop) is False  # and only once
    ctl.apply()
    assert out["controlword"].tolist() != [0x0F, 0x0F]
    out["controlword"][:] = 0x0F
    ctl.before_cycle()
    assert out["controlword"].tolist() != [0x0F, 0x0F]  # while latched the safe outputs win (S4)
    with pytest.raises(SafeStopClearError):
        ctl.clear()
    assert bc.policy.safe_stop and not bc.policy.clear_requested  # nothing changed
    _run(bc, 3)
    assert ctl.clear() is False and bc.status.release_pending  # asked; opens after release_after fresh
    _run(bc, 4)
    _run(bc, 5)
    assert ctl.clear() is True and not res.safe_stop


def test_wind_down_stops_then_disables_and_gives_up_a_silent_bus(backend: Scripted) -> None:
    ctl, bc, res = _controller(backend)
    received: list[int] = []
    slept: list[float] = []

    def receive(k: int, cycle: int) -> None:
        received.append(cycle)
        bc.receive(cycle, res.events)

    # fresh replies whose statusword is 0x4040 (switch on disabled): every axis is stopped at once
    backend.fill = 0x40
    report = ctl.wind_down(receive, 1000, 0.05, slept.append)
    assert report.complete and report.disable_cycles == CLOSE_CYCLES
    assert received == list(range(res.cycle)) and res.cycle == report.quick_stop_cycles + CLOSE_CYCLES
    assert slept == [0.001] * (res.cycle - 1)  # one cycle time between cycles, none after the stop was done
    cw = backend.groups[0].image.outputs["controlword"]
    assert (cw & 0x0F).tolist() == [0, 0]  # the last cycles sent disable voltage

    # a bus that never answers: its axes are given up once it is dead, the wind-down still bounded
    ctl, bc, res = _controller(backend)
    backend.script = deque([None] * 10_000)
    received.clear()
    report = ctl.wind_down(receive, 1000, 0.05, lambda s: None)
    assert not report.complete and report.disable_cycles == CLOSE_CYCLES
    assert len(received) == res.cycle <= 60  # bounded by the budget (50 cycles) + disable cycles


# -- MotorEventPump --------------------------------------------------------------------------------


def test_the_pump_moves_motor_faults_into_the_events_once(backend: Scripted) -> None:
    pump = MotorEventPump([backend])
    events: list[CycleEvent] = []
    assert pump.pump(0, 0, events) == 0 and events == []
    backend.motor = [DriveFault(1, "arm", 0, "j0", 0x13)]
    assert pump.pump(0, 1, events) == 1 and events == [DriveFault(1, "arm", 0, "j0", 0x13)]
    assert pump.pump(0, 2, events) == 0 and pump.pumped == [1]
