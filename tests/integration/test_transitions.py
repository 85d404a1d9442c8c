"""No transition starts motion (invariant S11 of docs/safety.md), on the in-process EtherCAT emulator.

Virtual time, 1 ms per exchange: every figure is in cycles. The judge is the emulated drive's own
physics (its velocity and position, its fault count), not what the master believes it sent. The
user's loop writes nothing after the transition: whatever moves the drive then was started by the
transition itself.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import yaml

import fieldbus
from fieldbus.commands.demo import DEMO_MAP
from fieldbus.core.acyclic_modes import AcyclicModes
from fieldbus.core.cia402 import Cia402Controller, Goal, Mode, State402
from fieldbus.platform.clock import VirtualClock

STILL_RAD_S = 0.05  # the drive's own |velocity| at or under this is standing still


def csv_map_without_modes(tmp_path: Path, *, modes_in_pdos: bool = False) -> Path:
    """The demo joint with target_velocity (0x60FF) in its RxPDOs and 0x6060/0x6061 only by SDO
    (``modes_in_pdos``: in the PDOs, target_torque left out for room)."""
    doc = yaml.safe_load(Path(DEMO_MAP).read_text())
    drop = (0x6071,) if modes_in_pdos else (0x6060, 0x6061)
    for section in ("rpdo", "tpdo"):
        for pdo in doc[section]:
            pdo["channels"] = [c for c in pdo["channels"] if c["index"] not in drop]
    doc["rpdo"][1]["channels"].append(
        {"index": 0x60FF, "sub_index": 0, "type": "int32", "factor": 20860.7568, "unit": "rad/s"}
    )
    doc["name"] = "joint_csv" if modes_in_pdos else "joint_csv_no_modes"
    f = tmp_path / f"{doc['name']}.yaml"
    f.write_text(yaml.safe_dump(doc, sort_keys=False))
    return f


def open_sim(tmp_path: Path, drive_map: Path, count: int = 1) -> tuple[fieldbus.Network, VirtualClock]:
    f = tmp_path / "net.yaml"
    m = json.dumps(str(drive_map))
    f.write_text(
        "cycle_time_us: 1000\nreceive_timeout_us: 5000\nsafe_stop_after: 4\nbuses:\n"
        f"  - {{name: arm, type: ethercat, interface: sim0, slaves: [{{name: 'j{{i}}', map: {m}, count: {count}}}]}}\n"
    )
    clock = VirtualClock()
    return fieldbus.open_network(f, backend="sim", clock=clock, release_after=3), clock


class Watch:
    """The emulated drives' own motion per cycle: peak |velocity| and travel since :meth:`mark`."""

    def __init__(self, drives: list[Any]) -> None:
        self.drives = drives
        self.mark()

    def mark(self) -> None:
        self.start = [d.position_rad for d in self.drives]
        self.peak = [0.0 for _ in self.drives]
        self.faults = [0 for _ in self.drives]
        self._was_fault = [d.state == State402.FAULT for d in self.drives]

    def sample(self) -> None:
        for i, d in enumerate(self.drives):
            self.peak[i] = max(self.peak[i], abs(d.velocity_rad_s))
            fault = d.state in (State402.FAULT, State402.FAULT_REACTION_ACTIVE)
            self.faults[i] += fault and not self._was_fault[i]
            self._was_fault[i] = fault

    def travel(self, i: int = 0) -> float:
        return abs(self.drives[i].position_rad - self.start[i])


def cycles(
    op: fieldbus.Operational,
    clock: VirtualClock,
    n: int,
    step: Callable[[fieldbus.CycleResult], None],
    watch: Watch | None = None,
) -> fieldbus.CycleResult:
    res = op.result
    for _ in range(n):
        clock.advance(1_000_000)
        res = op.exchange()
        step(res)
        if watch is not None:
            watch.sample()
    return res


def test_a_power_cycle_under_acyclic_modes_then_clear_starts_no_motion(tmp_path: Path) -> None:
    """Issue 33 item 6: CSV by SDO, a power cycle (the recovery writes 0x6060 = CSP), clear_safe_stop.

    Before: AcyclicModes still showed CSV (cached, never read again), the controller enabled a drive
    really in CSP and it chased the stale CSP target: 55.6 rad/s peak, 11.3 rad travel, 3 following-
    error faults. Now the display is read again before the enable, every target is seeded from the
    actual value, and the drive stays where it is."""
    net, clock = open_sim(tmp_path, csv_map_without_modes(tmp_path))
    try:
        op = net.bring_up()
        img = op["arm"]
        drive = net.backend("arm").chain.slaves[0].app  # type: ignore[attr-defined]
        ctrl = Cia402Controller(1, mode=Mode.CSP)
        modes = AcyclicModes.for_group(op, "arm")
        ctrl.set_goal(Goal.ENABLE)

        def step(res: fieldbus.CycleResult) -> None:
            ctrl.step_image(img, modes=modes)

        cycles(op, clock, 50, step)
        assert ctrl.all_reached and drive.mode_display == Mode.CSP
        ctrl.request_mode(Mode.CSV)
        cycles(op, clock, 20, step)
        assert drive.mode_display == Mode.CSV and modes.display[0] == Mode.CSV

        def run_csv(res: fieldbus.CycleResult) -> None:
            ctrl.step_image(img, modes=modes)
            img.outputs["target_velocity"][:] = 10.0  # rad/s, the user's command (then never again)

        cycles(op, clock, 1000, run_csv)
        assert drive.velocity_rad_s > 9.0 and abs(drive.position_rad) > 9.0  # 10 rad from the CSP target

        net.backend("arm").chain.power_cycle(0)  # type: ignore[attr-defined]
        res = cycles(op, clock, 5, step)
        assert res.safe_stop
        for _ in range(2000):  # the recovery brings it back, written with its start-up SDOs (CSP)
            res = cycles(op, clock, 1, step)
            if res.fresh and res.buses[0].consecutive_misses == 0 and not res.buses[0].recovering:
                break
        cycles(op, clock, 5, step)
        assert drive.mode_display == Mode.CSP  # the drive's own mode after its recovery
        watch = Watch([drive])
        assert op.clear_safe_stop() or cycles(op, clock, 5, step, watch) is not None
        opened = False
        for _ in range(20):
            opened = opened or op.clear_safe_stop()
            cycles(op, clock, 1, step, watch)
        assert opened and not op.result.safe_stop
        cycles(op, clock, 1500, step, watch)  # the user writes nothing after the clear
        print(
            f"after the clear: peak {watch.peak[0]:.1f} rad/s, travel {watch.travel():.1f} rad, faults {watch.faults}"
        )
        assert watch.peak[0] <= STILL_RAD_S, f"peak {watch.peak[0]:.1f} rad/s after the clear"
        assert watch.travel() < 0.01, f"travel {watch.travel():.2f} rad after the clear"
        assert watch.faults == [0] and ctrl.fault_resets[0] == 0
        assert ctrl.all_reached and drive.state == State402.OPERATION_ENABLED  # enabled again
        assert modes.forgotten[0] > 0 and modes.display[0] == Mode.CSV == drive.mode_display  # read again
    finally:
        net.close()


def test_enable_in_csv_while_the_joint_coasts_commands_zero_velocity_not_the_coasting_one(
    tmp_path: Path,
) -> None:
    """Enable without a command in CSV: before, target_velocity was seeded from velocity_actual_value, so
    a joint enabled while it coasted was driven on at that speed for ever. Now the seed is 0 and every
    other target (target_position here) is seeded too; the user's next write takes over."""
    net, clock = open_sim(tmp_path, csv_map_without_modes(tmp_path, modes_in_pdos=True))
    try:
        op = net.bring_up()
        img = op["arm"]
        drive = net.backend("arm").chain.slaves[0].app  # type: ignore[attr-defined]
        ctrl = Cia402Controller(1, mode=Mode.CSV)
        ctrl.set_goal(Goal.ENABLE)

        def step(res: fieldbus.CycleResult) -> None:
            ctrl.step_image(img)

        def run(res: fieldbus.CycleResult) -> None:
            ctrl.step_image(img)
            img.outputs["target_velocity"][:] = 10.0

        cycles(op, clock, 30, step)
        assert ctrl.all_reached and drive.mode_display == Mode.CSV
        cycles(op, clock, 500, run)
        ctrl.set_goal(Goal.DISABLE)  # power off: it coasts
        img.outputs["target_position"][:] = 123.0  # a stale command of another mode, written before
        cycles(op, clock, 30, step)
        assert drive.velocity_rad_s > 2.0 and ctrl.all_reached
        ctrl.set_goal(Goal.ENABLE)  # enable while it still coasts; the user writes nothing
        watch = Watch([drive])
        cycles(op, clock, 20, step, watch)
        assert abs(img.outputs["target_position"][0] - img.inputs["position_actual_value"][0]) < 0.5
        cycles(op, clock, 1000, step, watch)
        print(f"after the enable: |velocity| {abs(drive.velocity_rad_s):.2f} rad/s")
        assert abs(drive.velocity_rad_s) <= STILL_RAD_S, (
            f"{drive.velocity_rad_s:.2f} rad/s, 1 s after the enable"
        )
        assert ctrl.all_reached and not ctrl.seeded[0] and img.outputs["target_velocity"][0] == 0.0
        cycles(op, clock, 300, run)  # a command written after the transition counts
        assert drive.velocity_rad_s > 9.0
    finally:
        net.close()


def test_a_power_cycle_under_acyclic_modes_then_clear_starts_no_motion_on_canopen(tmp_path: Path) -> None:
    """Issue 33 item 6 on CANopen (reported there at 109 rad/s): our CANopen backend on python-can's
    virtual bus against the CANopen emulator; the node reset (NMT 0x81) restarts its drive and the
    recovery writes the start-up SDOs (0x6060 = CSP). Counted in cycles: the emulator steps its drive
    once per SYNC, so the drive's physics follow the cycles whatever the machine's load."""
    import can

    from sim_slaves.canopen import CanopenSimulator

    map_file = csv_map_without_modes(tmp_path)
    drive_map = fieldbus.load_drive_map(map_file)
    channel = f"fb-transitions-{tmp_path.name}"
    f = tmp_path / "net.yaml"
    f.write_text(
        "cycle_time_us: 5000\nreceive_timeout_us: 50000\nsafe_stop_after: 4\nbuses:\n"
        f"  - {{name: bus, type: canopen, interface: {channel}, can_interface: virtual,\n"
        f"     slaves: [{{name: j, map: {json.dumps(str(map_file))}, node_id: 5}}]}}\n"
    )
    with (
        can.Bus(interface="virtual", channel=channel) as bus,
        CanopenSimulator(bus, [(drive_map, 5)], dt_s=0.005) as sim,
        fieldbus.open_network(f, release_after=3) as net,
    ):
        op = net.bring_up()
        img = op["bus"]
        ctrl = Cia402Controller(1, mode=Mode.CSP)
        modes = AcyclicModes.for_group(op, "bus")
        ctrl.set_goal(Goal.ENABLE)
        command: list[float | None] = [None]

        def run(n: int, until: Callable[[], bool] = lambda: False, watch: Watch | None = None) -> bool:
            for _ in range(n):
                op.exchange()
                ctrl.step_image(img, modes=modes)
                if command[0] is not None:
                    img.outputs["target_velocity"][:] = command[0]
                if watch is not None:
                    watch.sample()
                if until():
                    return True
            return False

        assert run(600, lambda: ctrl.all_reached and modes.settled)
        ctrl.request_mode(Mode.CSV)
        assert run(600, lambda: ctrl.all_reached and modes.settled and modes.display[0] == Mode.CSV)
        drive = sim.node(5).app
        command[0] = 10.0  # rad/s, the user's command
        run(250)
        command[0] = None  # the user writes nothing from here on
        assert drive.velocity_rad_s > 9.0 and abs(drive.position_rad) > 9.0
        sim.power_cycle(5)
        assert run(400, lambda: op.result.safe_stop)
        assert run(3000, lambda: net.backend("bus").recoveries > 0 and op.result.fresh)

        def clear() -> bool:
            # the emulator answers from a thread on the wall clock: on a loaded machine a reply can come
            # later than receive_timeout_us, a miss. A clear then is refused (docs/safety.md S4) and the
            # latch holds; the operator asks again once the bus is fresh
            if not op.result.fresh:
                with pytest.raises(fieldbus.SafeStopClearError):
                    op.clear_safe_stop()
                assert op.result.safe_stop
                return False
            return op.clear_safe_stop()

        assert run(3000, clear)
        drive = sim.node(5).app  # the drive after its restart
        watch = Watch([drive])
        run(600, watch=watch)
        print(f"after the clear: peak {watch.peak[0]:.1f} rad/s, travel {watch.travel():.2f} rad")
        assert watch.peak[0] <= STILL_RAD_S, f"peak {watch.peak[0]:.1f} rad/s after the clear"
        assert watch.travel() < 0.01 and watch.faults == [0]
        assert ctrl.all_reached and modes.display[0] == Mode.CSV
        assert sim.node(5).od.get_value(0x6061, 0) == Mode.CSV  # the drive's own mode: written again
    assert not sim.errors
