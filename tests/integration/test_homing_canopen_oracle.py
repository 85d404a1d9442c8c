"""The independent oracle for homing: canopen's own ``BaseNode402`` on our CANopen emulator.

canopen (the package, not this library) reads the PDO configuration over SDO,
switches the operation mode through its ``op_mode`` property (0x6060 in an
RPDO, confirmed from 0x6061 in a TPDO, 0x6502 consulted first), enables the
drive and runs its ``homing()`` method (controlword bit 4, statusword bits
10/12/13). The same emulated drive, homed by this library's ``Homing`` over our
CANopen backend, must end at the same position. Both runs configure the drive
from the same map's ``homing:`` section (method 17: the negative switch, which
reads the home offset). Timing: python-can's virtual bus is threads in one
process, so canopen's own waits are wall-clock; the check is on positions.
"""

from __future__ import annotations

import itertools
import json
import time
from pathlib import Path

import numpy as np
import pytest

import fieldbus
from fieldbus import Cia402Controller, Goal, Homing, Mode
from fieldbus.core.cia402 import HomingPhase

can = pytest.importorskip("can")
canopen = pytest.importorskip("canopen")

from canopen.profiles.p402 import BaseNode402  # noqa: E402

from sim_slaves.canopen import CanopenSimulator  # noqa: E402
from sim_slaves.canopen.eds import to_canopen_od  # noqa: E402

pytestmark = pytest.mark.timeout(120)
DEMO_MAP = Path(fieldbus.__file__).resolve().parent / "data" / "demo_joint.yaml"
OFFSET = 10_000  # counts at the home point
CYCLE_S = 0.005
_channels = itertools.count()


def _map(tmp_path: Path) -> Path:
    f = tmp_path / "joint.yaml"
    f.write_text(
        DEMO_MAP.read_text()
        + f"homing: {{method: 17, offset: {OFFSET}, speeds: {{switch: 100000, zero: 10000}}}}\n"
    )
    return f


def _channel() -> str:
    return f"fb-oracle-{next(_channels)}-{time.monotonic_ns()}"


def _home_with_canopen(map_file: Path) -> int:
    """canopen's BaseNode402 homes node 5 and switches it CSP -> CSV -> CSP; returns 0x6064 after homing."""
    drive = fieldbus.load_drive_map(map_file)
    channel = _channel()
    with (
        can.Bus(interface="virtual", channel=channel) as bus,
        CanopenSimulator(bus, [(drive, 5)], dt_s=CYCLE_S) as sim,
    ):
        network = canopen.Network()
        network.connect(interface="virtual", channel=channel)
        try:
            node = BaseNode402(5, to_canopen_od(sim.node(5).od))
            network.add_node(node)
            # canopen's SDO client waits 0.3 s for a reply by default; our simulator answers from a
            # thread on the wall clock, which a loaded machine can deschedule for longer. The oracle's
            # own patience is its configuration (CiA 301 sets no SDO timeout), not what is judged.
            node.sdo.RESPONSE_TIMEOUT = 5.0
            node.nmt.state = "PRE-OPERATIONAL"
            for sdo in drive.sdo:  # the start-up writes, as canopen's user would make them
                node.sdo.download(sdo.index, sdo.sub_index, sdo.data)
            node.setup_402_state_machine(read_pdos=True)
            node.nmt.state = "OPERATIONAL"
            network.sync.start(CYCLE_S)
            for rpdo in node.rpdo.values():
                if rpdo.enabled:
                    rpdo.start(CYCLE_S)
            # canopen's RPDO holds 0x6060 = 0 (NO MODE) until its user sets one
            node.op_mode = "CYCLIC SYNCHRONOUS POSITION"
            assert node.op_mode == "CYCLIC SYNCHRONOUS POSITION"
            assert node.homing(timeout=10) is True
            assert node.op_mode == "HOMING"
            time.sleep(0.2)  # let it come to rest at the home point
            homed = int.from_bytes(node.sdo.upload(0x6064, 0), "little", signed=True)
            # switch modes through canopen's API: CSV, then CSP from where the joint is (no jump)
            node.rpdo_pointers[0x607A].raw = node.tpdo_values[0x6064]
            node.op_mode = "CYCLIC SYNCHRONOUS VELOCITY"
            assert node.op_mode == "CYCLIC SYNCHRONOUS VELOCITY"
            node.op_mode = "CYCLIC SYNCHRONOUS POSITION"
            assert node.op_mode == "CYCLIC SYNCHRONOUS POSITION"
            assert node.state == "OPERATION ENABLED"
            assert sim.node(5).od.get_value(0x6061, 0) == 8
            network.sync.stop()
        finally:
            network.disconnect()
    assert not sim.errors
    return homed


def _home_with_fieldbus(map_file: Path, tmp_path: Path) -> int:
    drive = fieldbus.load_drive_map(map_file)
    channel = _channel()
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
        homing = Homing.from_maps(ctrl, [drive], op.cycle_time_us)
        homing.start()
        for _ in range(3000):
            if not op.exchange().fresh:
                continue
            ctrl.step_image(img)
            homing.step(img.inputs["statusword"], img.outputs["controlword"])
            if homing.done and ctrl.all_reached:
                break
        assert homing.phase[0] == HomingPhase.DONE and ctrl.all_reached
        for _ in range(40):  # at rest, in CSP, holding where it is
            op.exchange()
            ctrl.step_image(img)
        homed = int(sim.node(5).od.get_value(0x6064, 0))
        assert np.all(img.inputs["modes_of_operation_display"] == Mode.CSP)
    assert not sim.errors
    return homed


def test_canopen_base_node_402_homes_our_emulator_and_our_homing_ends_at_the_same_position(
    tmp_path: Path,
) -> None:
    theirs = _home_with_canopen(_map(tmp_path))
    ours = _home_with_fieldbus(_map(tmp_path), tmp_path)
    # each stopped just past the switch, which reads OFFSET; 200 counts = 10 mrad
    assert abs(theirs - OFFSET) < 200 and abs(ours - OFFSET) < 200, (theirs, ours)
    assert abs(theirs - ours) < 200, (theirs, ours)
