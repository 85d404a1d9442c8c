"""The independent oracle for the profile modes: canopen's own ``BaseNode402`` on our CANopen emulator.

canopen (the package, not this library) configures the drive over SDO (0x6081
profile velocity, 0x6083/0x6084 acceleration/deceleration, from the map's
start-up writes), switches the operation mode through its ``op_mode`` property
(0x6502 consulted first), enables the drive with its ``state`` property and
runs the PP set-point handshake through its ``controlword``/``statusword``
properties (bit 4 up, wait for bit 12, bit 4 down, wait for bit 10), the target
in its RPDO (``rpdo_pointers``); then a PV move (0x60FF by SDO: the demo map
does not map it). The same emulated drive, moved by this library's ``ProfileMove``
over our CANopen backend, must end on the same target. Timing: python-can's
virtual bus is threads in one process, so canopen's waits are wall-clock; the
checks are on positions and velocities.
"""

from __future__ import annotations

import itertools
import json
import time
from collections.abc import Callable
from pathlib import Path

import pytest

import fieldbus
from fieldbus import Cia402Controller, Goal, Mode, ProfileMove, ProfilePhase

can = pytest.importorskip("can")
canopen = pytest.importorskip("canopen")

from canopen.profiles.p402 import BaseNode402  # noqa: E402

from sim_slaves.canopen import CanopenSimulator  # noqa: E402
from sim_slaves.canopen.eds import to_canopen_od  # noqa: E402

pytestmark = pytest.mark.timeout(120)
DEMO_MAP = Path(fieldbus.__file__).resolve().parent / "data" / "demo_joint.yaml"
CYCLE_S = 0.005
TARGET = 60_000  # counts (~0.46 rev)
SPEED = 40_000  # PV target [counts/s]
WINDOW = 100  # 0x6067 position window of the emulated drive [counts]
_channels = itertools.count()


def _map(tmp_path: Path) -> Path:
    f = tmp_path / "joint.yaml"
    f.write_text(
        DEMO_MAP.read_text()
        + "motion_profile: {velocity: 100000, acceleration: 400000, deceleration: 400000}\n"
    )
    return f


def _wait(what: Callable[[], bool], timeout_s: float = 10.0) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if what():
            return True
        time.sleep(0.002)
    return False


def test_canopen_base_node_402_runs_a_pp_and_a_pv_move_on_our_emulator(tmp_path: Path) -> None:
    drive = fieldbus.load_drive_map(_map(tmp_path))
    channel = f"fb-profile-oracle-{next(_channels)}-{time.monotonic_ns()}"
    with (
        can.Bus(interface="virtual", channel=channel) as bus,
        CanopenSimulator(bus, [(drive, 5)], dt_s=CYCLE_S) as sim,
    ):
        network = canopen.Network()
        network.connect(interface="virtual", channel=channel)
        try:
            node = BaseNode402(5, to_canopen_od(sim.node(5).od))
            network.add_node(node)
            node.sdo.RESPONSE_TIMEOUT = 3.0  # canopen's 0.3 s is short beside the suite's CPU burners
            # and its 0.5 s for 0x6061 to show a new mode: beside four burners the PV switch read back PP
            # (canopen logs the timeout and returns); the mode is still asserted after each switch
            node.TIMEOUT_SWITCH_OP_MODE = 5.0
            node.nmt.state = "PRE-OPERATIONAL"
            for sdo in drive.sdo:  # the start-up writes, as canopen's user would make them
                node.sdo.download(sdo.index, sdo.sub_index, sdo.data)
            assert node.sdo[0x6081].raw == 100_000 and node.sdo[0x6084].raw == 400_000
            node.setup_402_state_machine(read_pdos=True)
            node.nmt.state = "OPERATIONAL"
            network.sync.start(CYCLE_S)
            for rpdo in node.rpdo.values():
                if rpdo.enabled:
                    rpdo.start(CYCLE_S)
            node.op_mode = "PROFILED POSITION"
            assert node.op_mode == "PROFILED POSITION"
            node.state = "OPERATION ENABLED"
            assert node.state == "OPERATION ENABLED"
            start = node.tpdo_values[0x6064]
            # PP: the set-point handshake, through canopen's controlword/statusword properties
            node.rpdo_pointers[0x607A].raw = TARGET
            node.controlword = 0x001F  # enable operation + bit 4 new set-point (absolute, single)
            assert _wait(lambda: node.statusword & 0x1000 != 0), "no set-point acknowledge (bit 12)"
            node.controlword = 0x000F  # bit 4 down: the drive drops bit 12
            assert _wait(lambda: node.statusword & 0x1400 == 0x0400), "no target reached (bit 10)"
            time.sleep(0.1)  # at rest on the target
            reached = node.tpdo_values[0x6064]
            # PV: ramp to SPEED, at speed (bit 10), then back to 0 (bit 12: speed = 0)
            node.op_mode = "PROFILED VELOCITY"
            assert node.op_mode == "PROFILED VELOCITY"
            node.sdo[0x60FF].raw = SPEED
            assert _wait(lambda: node.statusword & 0x0400 != 0 and node.tpdo_values[0x606C] > SPEED // 2)
            at_speed = node.tpdo_values[0x606C]
            node.sdo[0x60FF].raw = 0
            assert _wait(lambda: node.statusword & 0x1400 == 0x1400), "no standstill (bits 10, 12)"
            stopped = node.tpdo_values[0x606C]
            assert node.state == "OPERATION ENABLED"
            network.sync.stop()
        finally:
            network.disconnect()
    assert not sim.errors
    assert abs(start) < WINDOW
    assert abs(reached - TARGET) <= WINDOW, reached
    assert abs(at_speed - SPEED) <= 1000, at_speed  # 0x606D velocity window
    assert abs(stopped) <= 1000, stopped


def test_our_profile_move_over_our_canopen_backend_ends_where_canopen_does(tmp_path: Path) -> None:
    map_file = _map(tmp_path)
    drive = fieldbus.load_drive_map(map_file)
    channel = f"fb-profile-ours-{next(_channels)}-{time.monotonic_ns()}"
    net_file = tmp_path / "net.yaml"
    net_file.write_text(
        "cycle_time_us: 5000\nreceive_timeout_us: 50000\nbuses:\n"
        f"  - {{name: bus, type: canopen, interface: {channel}, can_interface: virtual,\n"
        f"     slaves: [{{name: j, map: {json.dumps(str(map_file))}, node_id: 5}}]}}\n"
    )
    with (
        can.Bus(interface="virtual", channel=channel) as bus,
        CanopenSimulator(bus, [(drive, 5)], dt_s=CYCLE_S) as sim,
        fieldbus.open_network(net_file) as net,
    ):
        op = net.bring_up()
        img = op["bus"]
        ctrl = Cia402Controller(1, mode=Mode.CSP)
        ctrl.set_goal(Goal.ENABLE)
        moves = ProfileMove.from_maps(ctrl, [drive], op.cycle_time_us)
        for _ in range(3000):
            if op.exchange().fresh:
                ctrl.step_image(img)
                moves.step_image(img)
                if ctrl.all_reached:
                    break
        start = int(sim.node(5).od.get_value(0x6064, 0))
        moves.move_to(TARGET / 20860.7568)  # the map's factor: rad
        for _ in range(3000):
            if op.exchange().fresh:
                ctrl.step_image(img)
                moves.step_image(img)
                if moves.done:
                    break
        assert moves.phase[0] == ProfilePhase.DONE
        reached = int(sim.node(5).od.get_value(0x6064, 0))
        assert int(img.inputs["modes_of_operation_display"][0]) == Mode.PROFILE_POSITION
    assert not sim.errors
    assert abs(start) < WINDOW
    assert abs(reached - TARGET) <= WINDOW, reached  # where canopen's BaseNode402 took it (test above)
