"""The safety contract (docs/safety.md), one test per defect the review of issue 23 reproduced.

Each test fails on the code before the contract was enforced. The EtherCAT
ones run the in-process emulator (the sim backend: real frames against the
emulated ESC chain and CiA 402 drives, an independent implementation of the
slave side); the CAN one the raw-CAN backend against the MIT motor emulator on
python-can's virtual bus. Behaviour is asserted in cycles, never in wall time.
"""

from __future__ import annotations

import itertools
import json
import os
import struct
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest

import fieldbus
from fieldbus.commands.demo import DEMO_MAP
from fieldbus.core.cia402 import Cia402Controller, Goal, Mode, State402
from fieldbus.core.drivefault import DriveFault
from fieldbus.core.safety import SafeStopClearError, Verdict
from fieldbus.errors import RequestError
from fieldbus.network import BusEvent
from fieldbus.platform.clock import VirtualClock

MIT_MAP = Path(__file__).resolve().parents[2] / "pdo_maps" / "cubemars_ak80_9_mit.yaml"
_channels = itertools.count()


def _net_file(tmp_path: Path, *, axes: int = 2, safe_stop_after: int = 5, extra: str = "") -> Path:
    f = tmp_path / "net.yaml"
    m = json.dumps(str(DEMO_MAP))
    f.write_text(
        f"cycle_time_us: 1000\nreceive_timeout_us: 5000\nsafe_stop_after: {safe_stop_after}\nbuses:\n"
        f"  - {{name: arm, type: ethercat, interface: sim0, slaves: [{{name: 'j{{i}}', map: {m}, count: {axes}}}]}}\n"
        + extra
    )
    return f


@pytest.fixture
def enabled(tmp_path: Path) -> Iterator[tuple[fieldbus.Network, fieldbus.Operational, Cia402Controller]]:
    """A 2-axis arm on the in-process emulator, every axis in OPERATION ENABLED (CSP).

    The emulator runs on a virtual clock that advances 1 ms at the end of every exchange() (an
    observer), so the drives see the same time line on a busy machine as on a quiet one.
    """
    clock = VirtualClock()
    net = fieldbus.open_network(_net_file(tmp_path), backend="sim", clock=clock)
    try:
        op = net.bring_up()
        op.add_observer(_Tick(clock))
        ctrl = Cia402Controller(2, mode=Mode.CSP)
        ctrl.set_goal(Goal.ENABLE)
        img = op["arm"]
        for _ in range(300):
            op.exchange()
            ctrl.step(img.inputs["statusword"], img.outputs["controlword"])
            img.outputs["target_position"][:] = img.inputs["position_actual_value"]
            if ctrl.all_reached:
                break
        assert ctrl.all_reached, ctrl.state
        yield net, op, ctrl
    finally:
        net.close()


class _Tick:
    """An observer that lets one cycle time pass on a virtual clock after every exchange()."""

    def __init__(self, clock: VirtualClock, cycle_ns: int = 1_000_000) -> None:
        self.clock, self.cycle_ns = clock, cycle_ns

    def capture(self, res: fieldbus.CycleResult, t0_ns: int) -> None:
        self.clock.advance(self.cycle_ns)

    def note_events(self, events: list[Any]) -> None:
        pass

    def close(self) -> None:
        pass


def _chain(net: fieldbus.Network) -> Any:
    return net.backend("arm").chain  # type: ignore[attr-defined]  # the emulator's fault hooks


# -- defect 1: a safe stop cleared during an outage never latched again ----------------------------


def test_a_clear_during_an_outage_is_refused_and_the_latch_holds(enabled: Any) -> None:
    net, op, _ = enabled
    _chain(net).drop_frames(5000, process_data=True)
    for _ in range(5):
        res = op.exchange()
    assert res.safe_stop
    with pytest.raises(SafeStopClearError, match="during an outage: 5 consecutive misses"):
        op.clear_safe_stop()
    for k in range(1000):  # the bus stays dead: the latch never opens
        res = op.exchange()
        assert res.safe_stop and not res.fresh, k
    assert res.bus("arm").consecutive_misses == 1005


def test_a_clear_opens_the_latch_only_after_release_after_fresh_cycles(enabled: Any) -> None:
    net, op, _ = enabled
    _chain(net).drop_frames(5, process_data=True)
    for _ in range(5):
        op.exchange()
    assert op.result.safe_stop
    op.exchange()  # the bus is back: one fresh cycle
    assert op.result.fresh
    assert op.clear_safe_stop() is False  # asked; 1 of 10 fresh cycles so far
    released_at = None
    for k in range(20):
        res = op.exchange()
        if not res.safe_stop and released_at is None:
            released_at = k
    assert released_at == net.release_after - 2  # 1 fresh before the clear + 9 after it
    assert any(isinstance(e, BusEvent) and e.kind == "released" for e in op.result.events) or released_at


# -- defect 2: inputs flagged stale still changed ---------------------------------------------------


def test_stale_inputs_never_change_while_the_reply_is_rejected(enabled: Any) -> None:
    net, op, ctrl = enabled
    img = op["arm"]
    for k in range(50):  # move, so that every input changes from cycle to cycle
        img.outputs["target_position"][:] = 0.002 * k
        op.exchange()
        ctrl.step(img.inputs["statusword"], img.outputs["controlword"])
    accepted_values = img.inputs.values.tobytes()
    accepted_wire = img.inputs.wire.tobytes()
    _chain(net).corrupt_wkc(-1, 3)  # three replies with a short working counter: the data did arrive
    for k in range(3):
        img.outputs["target_position"][:] = 0.1 + 0.002 * k
        res = op.exchange()
        assert res.bus("arm").verdict is Verdict.SHORT and not res.fresh
        assert img.inputs.values.tobytes() == accepted_values, k  # every channel, bit for bit
        assert img.inputs.wire.tobytes() == accepted_wire, k
    res = op.exchange()
    assert res.fresh and img.inputs.wire.tobytes() != accepted_wire  # accepted again: it moves on


# -- S1: a backend exception is a verdict, never an exception out of exchange() ---------------------


def test_a_backend_that_raises_is_a_miss_with_its_reason_and_latches_at_once(enabled: Any) -> None:
    net, op, _ = enabled
    b = net.backend("arm")
    real = b.receive
    calls = itertools.count()

    def receive() -> int | None:
        if next(calls) < 3:
            raise OSError(100, "Network is down")
        return real()

    b.receive = receive  # type: ignore[method-assign]
    res = op.exchange()  # does not raise
    st = res.bus("arm")
    assert st.verdict is Verdict.ERROR and res.safe_stop and st.consecutive_misses == 1
    assert st.error == "OSError: [Errno 100] Network is down" and st.errors == 1
    assert [e.kind for e in res.events if isinstance(e, BusEvent)] == ["bus_error", "safe_stop"]
    for _ in range(2):
        op.exchange()
    assert op.result.bus("arm").errors == 3
    res = op.exchange()  # back: the reason of the last error is kept, this cycle's is None
    assert res.fresh and res.safe_stop and res.bus("arm").error is None
    assert res.bus("arm").last_error == "OSError: [Errno 100] Network is down"


# -- defect 4: a CAN transmit error stopped the cycle without a safe stop ---------------------------


class _FlakyBus(can.BusABC):  # type: ignore[misc]
    """python-can's virtual bus whose send raises what socketcan raises with no node acknowledging."""

    def __init__(self, channel: str) -> None:
        self._inner = can.Bus(interface="virtual", channel=channel)
        self.fail = False
        super().__init__(channel=channel)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if self.fail:
            raise can.CanOperationError("Transmit buffer full")
        self._inner.send(msg, timeout)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return self._inner.recv(timeout), False

    def shutdown(self) -> None:
        self._inner.shutdown()
        super().shutdown()


def test_a_can_transmit_error_is_a_verdict_that_latches_and_close_does_not_raise(tmp_path: Path) -> None:
    from sim_slaves.mit_motor import MitMotorSimulator

    channel = f"fb-safety-{os.getpid()}-{next(_channels)}"
    f = tmp_path / "net.yaml"
    f.write_text(
        "cycle_time_us: 2000\nreceive_timeout_us: 20000\nsafe_stop_after: 4\nbuses:\n"
        f"  - {{name: legs, type: rawcan, interface: {channel}, can_interface: virtual,\n"
        f"     slaves: [{{name: 'm{{i}}', map: {MIT_MAP}, node_id: 1, count: 2}}]}}\n"
    )
    drive = fieldbus.load_drive_map(MIT_MAP)
    flaky = _FlakyBus(channel)
    try:
        with (
            can.Bus(interface="virtual", channel=channel) as sim_bus,
            MitMotorSimulator(sim_bus, [(drive, n) for n in (1, 2)], dt_s=0.002),
        ):
            net = fieldbus.open_network(f, bus_options={"legs": {"can_bus": flaky}})
            op = net.bring_up()
            for _ in range(5):
                assert op.exchange().fresh
            flaky.fail = True  # the cable is pulled
            res = op.exchange()  # no exception
            st = res.bus("legs")
            assert st.verdict is Verdict.ERROR and res.safe_stop and not res.fresh
            assert st.error is not None and "Transmit buffer full" in st.error
            net.close()  # the wind-down and the exit frames fail too: counted and kept, not raised
            b = net.backend("legs")
            assert b.tx_errors > 1  # type: ignore[attr-defined]
            assert "Transmit buffer full" in str(b.last_error)  # type: ignore[attr-defined]
    finally:
        flaky.shutdown()


# -- defect 5: a bad acyclic request poisoned the cycle for good ------------------------------------


def test_a_malformed_request_is_refused_at_the_door_and_the_cycle_runs_on(enabled: Any) -> None:
    _, op, _ = enabled
    errors: list[BaseException] = []

    def other_thread() -> None:
        for index, sub in ((0x10000, 0), (0x1018, 0x100), (-1, 0)):
            try:
                op.submit_sdo_read("arm", "j0", index, sub)
            except RequestError as exc:
                errors.append(exc)

    t = threading.Thread(target=other_thread)
    t.start()
    t.join()
    assert len(errors) == 3 and "SDO index 0x10000 out of range 0..0xFFFF" in str(errors[0])
    with pytest.raises(RequestError, match="bytes"):
        op.submit_sdo_write("arm", "j0", 0x2000, 0, b"")
    good = op.submit_sdo_read("arm", "j0", 0x1018, 1)
    for _ in range(5):
        assert op.exchange().fresh
    assert good.result(0) == (0xFB1).to_bytes(4, "little")


def test_a_request_that_fails_while_served_fails_alone_with_its_cause(enabled: Any) -> None:
    net, op, _ = enabled
    b = net.backend("arm")
    real = b.acyclic_step

    def broken(req: Any) -> bool:
        b.acyclic_step = real  # type: ignore[method-assign]  # once
        raise struct.error("argument out of range")

    b.acyclic_step = broken  # type: ignore[method-assign]
    bad = op.submit_sdo_read("arm", "j0", 0x1018, 1)
    after = op.submit_sdo_read("arm", "j1", 0x1018, 2)
    for _ in range(5):
        assert op.exchange().fresh
    with pytest.raises(fieldbus.FieldbusError, match=r"struct\.error: argument out of range"):
        bad.result(0)
    assert after.result(0) == (0xD01).to_bytes(4, "little")
    assert op.result.bus("arm").last_error == "struct.error: argument out of range"


# -- defect 6: close() let drives coast -------------------------------------------------------------


def test_close_holds_the_quick_stop_until_the_drive_has_stopped(tmp_path: Path) -> None:
    clock = VirtualClock()  # the emulated drives' time: 1 ms per cycle, whatever the machine's load
    net = fieldbus.open_network(_net_file(tmp_path, axes=1), backend="sim", clock=clock)
    op = net.bring_up()
    ctrl = Cia402Controller(1, mode=Mode.CSP)
    ctrl.set_goal(Goal.ENABLE)
    img = op["arm"]
    drive = _chain(net).slaves[0].app
    q = 0.0
    for k in range(800):
        clock.advance(1_000_000)
        op.exchange()
        ctrl.step(img.inputs["statusword"], img.outputs["controlword"])
        if ctrl.all_reached:
            q += 0.03 * min(1.0, k / 200)  # ramp up to 30 rad/s (1 kHz cycle)
            img.outputs["target_position"][:] = q
        else:
            img.outputs["target_position"][:] = img.inputs["position_actual_value"]
    assert float(img.inputs["velocity_actual_value"][0]) > 20.0
    net.close()
    report = net.last_wind_down
    assert report is not None and report.complete, report
    (axis,) = report.axes
    assert axis.how in ("stopped", "state") and axis.cycles > 50  # it waited for the ramp
    assert axis.velocity is not None and axis.velocity < 0.5
    # the emulated drive (its own state, not the master's view) stopped before power went off
    assert abs(drive.velocity_rad_s) < 0.5
    assert drive.state != State402.OPERATION_ENABLED


# -- defect 7: automatic fault reset looped silently ------------------------------------------------


def test_fault_resets_are_bounded_and_every_fault_is_an_event_with_its_code(enabled: Any) -> None:
    net, op, ctrl = enabled
    img = op["arm"]
    drive = _chain(net).slaves[1].app
    events: list[Any] = []
    for _ in range(2000):
        if drive.state == State402.OPERATION_ENABLED:
            drive.inject_fault(0x8611)  # a following error that comes back after every reset
        res = op.exchange()
        events += res.events
        ctrl.step(img.inputs["statusword"], img.outputs["controlword"])
        img.outputs["target_position"][:] = img.inputs["position_actual_value"]
    assert ctrl.fault_resets[1] == ctrl.max_fault_resets == 3 and ctrl.gave_up[1]
    assert ctrl.state[1] == State402.FAULT and ctrl.fault_resets[0] == 0
    faults = [e for e in events if isinstance(e, DriveFault)]
    # each fault edge is an event; the demo map has no 0x603F in its PDOs: read acyclically, then named
    assert res.drive_faults["arm"][1] == 4 and res.drive_faults["arm"][0] == 0  # first + 3 after resets
    named = [e for e in faults if e.code is not None]
    assert len(named) == 4 and all(e.code == 0x8611 and e.slave == "j1" for e in named)
    assert "following error" in str(named[0]).lower()


# -- defect 10: a network that failed validation leaked ---------------------------------------------


def test_a_network_that_fails_validation_opens_nothing(tmp_path: Path) -> None:
    channel = f"fb-atomic-{os.getpid()}-{next(_channels)}"
    m = json.dumps(str(DEMO_MAP))
    f = tmp_path / "net.yaml"
    f.write_text(
        "cycle_time_us: 1000\nbuses:\n"
        f"  - {{name: a, type: canopen, interface: {channel}, can_interface: virtual, cycle_time_us: 2000,"
        f" slaves: [{{name: n1, map: {m}, node_id: 1}}]}}\n"
        f"  - {{name: b, type: canopen, interface: {channel}x, can_interface: virtual, cycle_time_us: 3000,"
        f" slaves: [{{name: n2, map: {m}, node_id: 2}}]}}\n"
    )
    log = tmp_path / "a.asc"
    before = set(threading.enumerate())
    with pytest.raises(fieldbus.FieldbusError, match="not a whole multiple"):
        fieldbus.open_network(f, bus_options={"a": {"can_log": str(log)}})
    assert set(threading.enumerate()) <= before  # no log writer thread left behind
    assert not log.exists()  # nothing was opened


def test_the_safe_stop_writes_and_the_drive_is_held_in_quick_stop_while_latched(enabled: Any) -> None:
    net, op, _ = enabled
    _chain(net).drop_frames(5, process_data=True)
    for _ in range(5):
        op.exchange()
    for _ in range(50):
        res = op.exchange()
        assert res.safe_stop
    states = [int(s.app.state) for s in _chain(net).slaves]
    assert State402.OPERATION_ENABLED not in states
    assert np.all(op["arm"].outputs["controlword"] & 0x0F == 0x02)


# -- what was hidden, shown: one public observer interface -------------------------------------------


def test_faults_reach_the_observers_the_recording_the_monitor_and_the_report(
    enabled: Any, tmp_path: Path
) -> None:
    from fieldbus.operations.monitor import Monitor
    from fieldbus.operations.report import run_report
    from fieldbus.platform.timing import CycleTimer
    from fieldbus.recording import load

    net, op, ctrl = enabled
    img = op["arm"]
    seen: list[Any] = []

    class Probe:
        def capture(self, res: fieldbus.CycleResult, t0_ns: int) -> None:
            seen.append(res.cycle)

        def note_events(self, events: list[Any]) -> None:
            seen.extend(events)

        def close(self) -> None:
            seen.append("closed")

    probe = Probe()
    op.add_observer(probe)
    rec = op.record(tmp_path / "run.mcap")
    assert Monitor(op).snapshot()["buses"][0]["slaves"][0]["state"] == "OP"  # not SOEM's cached PRE-OP
    b = net.backend("arm")
    real = b.receive
    b.receive = lambda: (_ for _ in ()).throw(OSError(100, "Network is down"))  # type: ignore[method-assign]
    op.exchange()
    b.receive = real  # type: ignore[method-assign]
    _chain(net).slaves[0].app.inject_fault(0x2310)  # continuous over-current
    for _ in range(30):
        op.exchange()
        ctrl.step(img.inputs["statusword"], img.outputs["controlword"])
    rec.close()
    events = load(tmp_path / "run.mcap").events
    kinds = {e["kind"] for e in events}
    assert {"bus_error", "drive_fault", "safe_stop"} <= kinds, kinds
    assert any(e["kind"] == "drive_fault" and e["code"] == 0x2310 for e in events)
    assert any(isinstance(e, BusEvent) and e.kind == "bus_error" for e in seen)
    assert any(isinstance(e, DriveFault) and e.code == 0x2310 for e in seen)
    view = op.buses[0]
    assert view.counters()["errors"] == 1 and view.status.last_error == "OSError: [Errno 100] Network is down"
    report = run_report(op, CycleTimer(capacity=4), 1000.0)
    (bus,) = report["buses"]
    assert bus["errors"] == 1 and bus["drive_faults"] == {"arm": [1, 0]}
    net.close()
    assert seen[-1] == "closed"
