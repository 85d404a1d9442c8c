"""The controlled stop on close() (invariant S6 of docs/safety.md) under faults during the close itself.

EtherCAT on the in-process emulator in virtual time (1 ms per cycle; the wind-down's own waits pass
on the same clock), so every figure is in cycles. The judge is the emulated drives' own physics: the
velocity each drive had when the master's disable voltage reached it.
"""

from __future__ import annotations

import json
import threading
from pathlib import Path
from typing import Any

import pytest

import fieldbus
from fieldbus.commands.demo import DEMO_MAP
from fieldbus.core.al import AlState
from fieldbus.core.cia402 import Cia402Controller, Goal, Mode, State402
from fieldbus.platform.clock import VirtualClock

SPEED = 24.0  # rad/s of the drives when close() begins
STOPPED_RAD_S = 0.5  # the drive's own |velocity| when power goes off: it was stopped, not coasting


class SleepHook(VirtualClock):
    """A virtual clock that runs ``hook`` on its ``at``-th sleep (the wind-down sleeps once a cycle)."""

    def __init__(self) -> None:
        super().__init__()
        self.sleeps = 0
        self.at = -1
        self.hook: Any = None

    def sleep(self, seconds: float) -> None:
        self.sleeps += 1
        if self.sleeps == self.at and self.hook is not None:
            self.hook()
        super().sleep(seconds)


class PowerOff:
    """Per drive: its own |velocity| when it first left OPERATION ENABLED / QUICK STOP with power on."""

    def __init__(self, drives: list[Any]) -> None:
        self.drives = drives
        self.at: list[float | None] = [None] * len(drives)

    def sample(self) -> None:
        for i, d in enumerate(self.drives):
            powered = d.state in (State402.OPERATION_ENABLED, State402.QUICK_STOP_ACTIVE)
            if not powered and self.at[i] is None:
                self.at[i] = abs(d.velocity_rad_s)


def moving_arm(tmp_path: Path, clock: VirtualClock, axes: int = 2) -> tuple[fieldbus.Network, list[Any]]:
    """``axes`` demo joints on the emulator, enabled in CSP and moving at SPEED."""
    f = tmp_path / "net.yaml"
    m = json.dumps(str(DEMO_MAP))
    f.write_text(
        "cycle_time_us: 1000\nreceive_timeout_us: 5000\nsafe_stop_after: 10\nbuses:\n"
        f"  - {{name: arm, type: ethercat, interface: sim0, slaves: [{{name: 'j{{i}}', map: {m}, count: {axes}}}]}}\n"
    )
    net = fieldbus.open_network(f, backend="sim", clock=clock)
    op = net.bring_up()
    img = op["arm"]
    ctrl = Cia402Controller(axes, mode=Mode.CSP)
    ctrl.set_goal(Goal.ENABLE)
    speed = 0.0
    for _ in range(1500):
        clock.advance(1_000_000)
        op.exchange()
        ctrl.step_image(img)
        if ctrl.all_reached:
            speed = min(SPEED, speed + 0.04)  # 40 rad/s²
            img.outputs["target_position"][:] += speed * 1e-3
    drives = [s.app for s in net.backend("arm").chain.slaves]  # type: ignore[attr-defined]
    assert all(d.velocity_rad_s > SPEED - 1 for d in drives)
    return net, drives


def _watched(net: fieldbus.Network, drives: list[Any]) -> PowerOff:
    """Sample the drives after every frame of the close (the emulator's frames are its clock's steps)."""
    off = PowerOff(drives)
    backend = net.backend("arm")
    real = backend.receive

    def receive() -> int | None:
        got = real()
        off.sample()
        return got

    backend.receive = receive  # type: ignore[method-assign]
    return off


@pytest.mark.parametrize("comes_back", [True, False])
def test_a_power_cycled_slave_during_close_stops_the_healthy_drive_before_its_power_goes(
    tmp_path: Path, comes_back: bool
) -> None:
    """Issue 33 item 7: one slave power-cycled, close(). The reply arrives every cycle with a short
    working counter; before, the wind-down saw no row fresh, called both axes silent after 10 cycles
    and disabled the healthy drive at 24 rad/s (it coasted). Now the recovery's AL readings tell
    which slave answered: the healthy drive is watched to its stop, the power-cycled one given up.
    ``comes_back=False``: the power-cycled slave then refuses PRE-OP (its recovery never ends), so the
    healthy drive can only be seen through the per-slave rule, never through a full counter again."""
    clock = SleepHook()
    net, drives = moving_arm(tmp_path, clock)
    off = _watched(net, drives)
    chain = net.backend("arm").chain  # type: ignore[attr-defined]
    chain.power_cycle(1)
    if not comes_back:
        chain.refuse_state(1, AlState.PRE_OP, 0x0011)  # invalid requested state change
    net.close()
    report = net.last_wind_down
    assert report is not None
    healthy, cycled = report.axes
    print(f"healthy: {healthy}, power-cycled: {cycled}, drive 0 at power off {off.at[0]}")
    assert off.at[0] is not None and off.at[0] < STOPPED_RAD_S, f"disabled at {off.at[0]} rad/s"
    assert healthy.how == "stopped" and healthy.cycles > 50  # it waited for the ramp
    assert cycled.how in ("silent", "state", "stopped")
    if not comes_back:
        assert cycled.how == "silent" and chain.slaves[1].app.state != State402.OPERATION_ENABLED


def test_a_second_close_from_another_thread_waits_for_the_wind_down(tmp_path: Path) -> None:
    """Issue 33 item 8, from another thread: before, the second close() skipped the wind-down and
    stopped every backend while the first was quick-stopping: the drive left OP at 24 rad/s."""
    clock = SleepHook()
    net, drives = moving_arm(tmp_path, clock, axes=1)
    off = _watched(net, drives)
    outcome: list[object] = []  # the wind-down's report as the second close() found it on return

    def second() -> None:
        net.close()
        r = net.last_wind_down  # kept as it goes: before, no axis's outcome yet
        outcome.append(None if r is None else (r.complete, [a.how for a in r.axes]))

    t = threading.Thread(target=second)

    def start_second() -> None:
        t.start()
        t.join(1.0)  # before: long enough for it to stop every bus; now it waits for us

    clock.at, clock.hook = clock.sleeps + 5, start_second
    net.close()
    t.join()
    d = drives[0]
    assert off.at[0] is not None, f"left behind {State402(d.state).name} at {d.velocity_rad_s:.1f} rad/s"
    assert off.at[0] < STOPPED_RAD_S, f"power off at {off.at[0]:.1f} rad/s"
    # judged where the second close() returned, not by which thread the scheduler ran first afterwards
    assert outcome == [(True, ["stopped"])], outcome
    report = net.last_wind_down
    assert report is not None and report.complete and report.axes[0].how == "stopped", report


def test_a_second_close_from_a_signal_handler_does_not_cut_the_wind_down_short(tmp_path: Path) -> None:
    """Issue 33 item 8, re-entered in the same thread (a signal handler that calls close())."""
    clock = SleepHook()
    net, drives = moving_arm(tmp_path, clock, axes=1)
    off = _watched(net, drives)
    clock.at, clock.hook = clock.sleeps + 5, net.close
    net.close()
    d = drives[0]
    assert off.at[0] is not None, f"left behind {State402(d.state).name} at {d.velocity_rad_s:.1f} rad/s"
    assert off.at[0] < STOPPED_RAD_S, f"power off at {off.at[0]:.1f} rad/s"
    report = net.last_wind_down
    assert report is not None and report.complete and report.axes[0].how == "stopped", report
    assert clock.sleeps > clock.at + 50


def test_each_bus_winds_down_at_its_own_rate(tmp_path: Path) -> None:
    """Issue 33 item 9: a 4 ms CANopen bus beside a 1 ms EtherCAT bus. Before, the wind-down ran every
    bus every cycle: the CANopen bus sent a SYNC in each of the 228 cycles (4x its configured bus
    load). Counted on the CAN bus itself by a listener: at most one SYNC per 4 wind-down cycles."""
    import can

    from sim_slaves.canopen import CanopenSimulator

    channel = f"fb-winddown-{tmp_path.name}"
    m = json.dumps(str(DEMO_MAP))
    f = tmp_path / "net.yaml"
    f.write_text(
        "cycle_time_us: 1000\nreceive_timeout_us: 5000\nsafe_stop_after: 1000\nbuses:\n"
        f"  - {{name: arm, type: sim, interface: sim0, slaves: [{{name: 'j{{i}}', map: {m}, count: 1}}]}}\n"
        f"  - {{name: can, type: canopen, interface: {channel}, can_interface: virtual, cycle_time_us: 4000,\n"
        f"     slaves: [{{name: 'n{{i}}', map: {m}, node_id: 1, count: 1}}]}}\n"
    )
    drive_map = fieldbus.load_drive_map(DEMO_MAP)
    clock = VirtualClock()
    with (
        can.Bus(interface="virtual", channel=channel) as sim_bus,
        CanopenSimulator(sim_bus, [(drive_map, 1)], dt_s=0.004),
        can.Bus(interface="virtual", channel=channel) as listener,
    ):
        net = fieldbus.open_network(f, clock=clock)
        try:
            op = net.bring_up()
            img = op["arm"]
            ctrl = Cia402Controller(1, mode=Mode.CSP)
            ctrl.set_goal(Goal.ENABLE)
            speed = 0.0
            for _ in range(1200):
                clock.advance(1_000_000)
                op.exchange()
                ctrl.step_image(img)
                if ctrl.all_reached:
                    speed = min(SPEED, speed + 0.04)
                    img.outputs["target_position"][:] += speed * 1e-3
            while listener.recv(0) is not None:  # what went out before the close
                pass
        finally:
            net.close()
        syncs = 0
        while (msg := listener.recv(0)) is not None:
            syncs += msg.arbitration_id == 0x080
    report = net.last_wind_down
    assert report is not None
    cycles = report.quick_stop_cycles + report.disable_cycles
    print(f"wind-down: {cycles} cycles, {syncs} SYNCs on the 4 ms bus")
    assert cycles > 40  # the EtherCAT drive took its time to stop
    assert 0 < syncs <= cycles // 4 + 1, (syncs, cycles)
