"""fieldbus.testing on every raw-CAN family: each shipped map's own emulator, its faults by the family's codes.

The master is the real raw-CAN backend; the emulators are our own (sim_slaves), so these tests judge the
master's view (events, verdicts, inputs) against the families' published codes and names, written out
here (Damiao 0xE overload, ODrive MOTOR_OVER_TEMP 0x2000 on 0.6 and 0x800 WATCHDOG_TIMER_EXPIRED on 0.5,
CubeMars 2 over-current); the independent drivers' tests are tests/interop/test_*_oracle.py.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("can")

import fieldbus
from fieldbus.testing import EmulationError, FaultNotSupported, emulate

pytestmark = pytest.mark.timeout(300)
SAFE_STOP_AFTER = 10
TURN = 2 * math.pi
# per shipped map: the outputs that make the motors track a target, the target (the map's position
# unit), the fault code and the name the master must report
FAMILIES: dict[str, tuple[dict[str, float], float, int, str]] = {
    "damiao_dm_j4310": ({"kp": 20.0, "kd": 1.0}, 0.3, 0xE, "overload"),
    "odrive_s1": ({}, 0.3 / TURN, 0x2000, "MOTOR_OVER_TEMP"),
    "odrive_3_6": ({}, 0.3 / TURN, 0x800, "WATCHDOG_TIMER_EXPIRED"),
    "cubemars_ak80_9_servo": ({"speed_limit": 5.0}, 0.3, 2, "over-current"),
    "cubemars_ak10_9_mit": ({"kp": 20.0, "kd": 1.0}, 0.3, 2, "over-current"),
}


def _network(tmp_path: Path, maps: list[str], n: int = 2, name: str = "legs.yaml") -> Path:
    """A robot's network file: one raw-CAN bus on can0 with ``n`` motors of each map in ``maps``."""
    slaves = ", ".join(
        f"{{name: 'm{k}_{{i}}', map: '{fieldbus.PDO_MAPS / (m + '.yaml')}', node_id: {1 + k * n}, count: {n}}}"
        for k, m in enumerate(maps)
    )
    f = tmp_path / name
    f.write_text(
        f"cycle_time_us: 1000\nreceive_timeout_us: 500\nsafe_stop_after: {SAFE_STOP_AFTER}\nbuses:\n"
        f"  - {{name: legs, type: rawcan, interface: can0, can_interface: socketcan, slaves: [{slaves}]}}\n"
    )
    return f


def _scenario(net: Path, drive_map: str) -> dict[str, Any]:
    """Track a target, fault motor 1 by the family's code, then silence motor 0: what the master saw."""
    setup, target, code, _ = FAMILIES[drive_map]
    with emulate(net) as emu:
        op = emu.op
        legs = op["legs"]
        for key, value in setup.items():
            legs.outputs[key][:] = value
        legs.outputs["position"][:] = target
        events: list[tuple[int, Any]] = []

        def step(_k: int) -> None:
            result = op.exchange()
            events.extend((len(emu.trace) - 1, e) for e in result.events)  # by trace index

        emu.run(step, 1500)
        tracked = legs.inputs["position"].copy()
        fault_at = emu.trace.mark()
        emu.drive_fault("legs", "m0_1", code)
        emu.run(step, 20)
        silence_at = emu.trace.mark()
        emu.silence("legs", "m0_0")
        emu.run(step, 40)
        return {
            "tracked": tracked,
            "events": events,
            "fault_at": fault_at,
            "silence_at": silence_at,
            "arrays": {k: v.copy() for k, v in emu.trace.arrays().items()},
            "clock_ns": emu.clock.now_ns(),
        }


@pytest.mark.parametrize("drive_map", sorted(FAMILIES))
def test_each_family_tracks_faults_by_name_and_safe_stops_the_same_twice(
    tmp_path: Path, drive_map: str
) -> None:
    net = _network(tmp_path, [drive_map])
    first, second = _scenario(net, drive_map), _scenario(net, drive_map)
    _, target, code, name = FAMILIES[drive_map]
    # brought up and tracking the target on every motor
    assert np.all(np.abs(first["tracked"] - target) < 0.1 * abs(target)), first["tracked"]
    assert first["arrays"]["fresh"][: first["fault_at"]].all()
    # the fault arrives as one named MotorFaultEvent of motor m0_1, within a few cycles
    faults = [(k, e) for k, e in first["events"] if isinstance(e, fieldbus.DriveFault)]
    assert [(e.slave, e.code, e.name) for _, e in faults] == [("m0_1", code, name)], faults
    assert first["fault_at"] <= faults[0][0] < first["fault_at"] + 5
    # the silence latches the safe stop after exactly safe_stop_after missed cycles
    stops = first["arrays"]["safe_stop"][first["silence_at"] :]
    assert stops.any() and int(np.argmax(stops)) == SAFE_STOP_AFTER - 1 and stops[SAFE_STOP_AFTER - 1 :].all()
    # virtual time: the same cycles bit for bit on the second run
    assert first["clock_ns"] == second["clock_ns"] >= len(first["arrays"]["fresh"]) * 1_000_000
    assert first["arrays"].keys() == second["arrays"].keys()
    for key, value in first["arrays"].items():
        assert value.tobytes() == second["arrays"][key].tobytes(), key
    assert [(k, str(e)) for k, e in first["events"]] == [(k, str(e)) for k, e in second["events"]]


@pytest.mark.parametrize("drive_map", sorted(FAMILIES))
def test_each_family_on_the_wall_clock_comes_up_and_faults_by_name(tmp_path: Path, drive_map: str) -> None:
    """python-can's virtual bus, the emulator in its own thread: generous timeouts, no timing asserted."""
    setup, target, code, name = FAMILIES[drive_map]
    net = _network(tmp_path, [drive_map])
    with emulate(net, clock=fieldbus.testing.WallClock(), receive_timeout_us=50_000) as emu:
        assert not emu.virtual
        op = emu.op
        for key, value in setup.items():
            op["legs"].outputs[key][:] = value
        op["legs"].outputs["position"][:] = target
        emu.cycles(50)
        assert emu.trace.arrays()["fresh"].any()
        emu.drive_fault("legs", "m0_0", code)
        seen: list[tuple[str, int | None, str]] = []
        for _ in range(500):  # (a stalled master may also trip a Damiao's own 50 ms CAN timeout: 0xD)
            seen += [
                (e.slave, e.code, e.name) for e in op.exchange().events if isinstance(e, fieldbus.DriveFault)
            ]
            if ("m0_0", code, name) in seen:
                break
        assert ("m0_0", code, name) in seen, seen


def test_a_bus_mixing_families_is_refused_naming_the_bus_and_families(tmp_path: Path) -> None:
    net = _network(tmp_path, ["damiao_dm_j4310", "odrive_s1"])
    with (
        pytest.raises(EmulationError, match=r"bus 'legs'.*damiao \(damiao_dm_j4310\).*odrive \(odrive_s1\)"),
        emulate(net),
    ):
        pass


def test_a_bus_of_several_maps_of_one_family_runs(tmp_path: Path) -> None:
    net = _network(tmp_path, ["damiao_dm_j4310", "damiao_dm_j4340"])
    with emulate(net) as emu:
        emu.cycles(100)
        assert emu.trace.arrays()["fresh"].all()
        assert emu.op.result.bus("legs").wkc == 4


@pytest.mark.parametrize(
    ("drive_map", "code", "message"),
    [
        ("damiao_dm_j4310", 0x1, "0x8 over-voltage"),  # 1 is "enabled", a state
        ("cubemars_ak80_9_servo", 0x100, "0x6 phase current unbalance; got 0x100"),
        ("cubemars_ak80_9_servo", 0x7, "0x2 over-current"),  # not in the map's table
    ],
)
def test_a_fault_code_the_family_does_not_have_is_refused(
    tmp_path: Path, drive_map: str, code: int, message: str
) -> None:
    with (
        emulate(_network(tmp_path, [drive_map])) as emu,
        pytest.raises(fieldbus.FieldbusError, match=message),
    ):
        emu.drive_fault("legs", "m0_0", code)


def test_mit_motors_have_no_fault_code_and_families_without_corruption_say_so(tmp_path: Path) -> None:
    with (
        emulate(_network(tmp_path, ["cubemars_ak80_9_mit"])) as emu,
        pytest.raises(FaultNotSupported, match="no error code"),
    ):
        emu.drive_fault("legs", "m0_0", 1)
    with (
        emulate(_network(tmp_path, ["odrive_s1"])) as emu,
        pytest.raises(FaultNotSupported, match="odrive emulator sends no corrupted replies"),
    ):
        emu.corrupt_inputs("legs", "m0_0")


@pytest.mark.parametrize(
    ("drive_map", "field", "after"),
    [
        ("damiao_dm_j4310", "error", 0),  # disabled (0), no longer enabled (1)
        ("odrive_s1", "axis_state", 1),  # IDLE after the reboot
        ("cubemars_ak80_9_servo", "error", 0),  # running again, the fault gone
    ],
)
def test_a_power_cycle_reaches_the_family(tmp_path: Path, drive_map: str, field: str, after: int) -> None:
    """The family's power-up state, as the master reads it, and the replies going on."""
    with emulate(_network(tmp_path, [drive_map])) as emu:
        emu.cycles(200)
        if drive_map.startswith("cubemars"):
            emu.drive_fault("legs", "m0_0", 2)
            emu.cycles(5)
            assert emu.op["legs"].inputs["error"][0] == 2
        before = int(emu.op["legs"].inputs[field][0])
        emu.power_cycle("legs", "m0_0")
        emu.cycles(300)  # ODrive: a heartbeat at once (state changed), the next ones every 100 ms
        assert int(emu.op["legs"].inputs[field][0]) == after != before
        assert emu.trace.arrays()["fresh"][-50:].all()


@pytest.mark.parametrize("drive_map", sorted(FAMILIES))
def test_lose_cycles_loses_exactly_that_many_replies_of_each_family(tmp_path: Path, drive_map: str) -> None:
    with emulate(_network(tmp_path, [drive_map])) as emu:
        emu.cycles(100)
        since = emu.trace.mark()
        emu.lose_cycles("legs", 5)
        emu.cycles(20)
        verdicts = emu.trace.verdict("legs")[since:]
        timeout, ok = int(fieldbus.Verdict.TIMEOUT), int(fieldbus.Verdict.OK)
        assert (verdicts[:5] == timeout).all() and (verdicts[5:] == ok).all(), verdicts


def test_the_emulation_does_not_take_the_robot_s_can_channel(tmp_path: Path) -> None:
    """A master (or another test) holding can0 does not stop an emulation of a file that names can0."""
    from fieldbus.backends.buslock import lock_can_bus
    from fieldbus.core.network import load_network

    net = _network(tmp_path, ["odrive_s1"])
    held = lock_can_bus(load_network(net).buses[0])
    try:
        for clock in (None, fieldbus.testing.WallClock()):
            with emulate(net, clock=clock, receive_timeout_us=50_000) as emu:
                emu.cycles(20)
                assert emu.trace.arrays()["fresh"].any()
    finally:
        held.release()
