"""Emulated drives built from each shipped CiA 402 map, as it is, have the objects of every mode 0x6502
advertises, judged by independent masters.

A real EPOS4 or Elmo has 0x6098 (homing method), 0x607C (home offset), 0x6099/0x609A and the profile
objects (0x6081, 0x6083, 0x6084) whatever its master writes at start-up; before, our emulated drive had
them only when the map carried a ``homing:`` / ``motion_profile:`` section, and no shipped map has one,
so canopen's ``BaseNode402`` could not home one (SDO abort 0x06020000 on 0x6098 and 0x607C).

Oracles: canopen's ``BaseNode402`` (its SDO client, ``op_mode``, ``state``, ``homing()``, the PP
set-point handshake through ``controlword``/``statusword``) on our CANopen emulator, for every shipped
CiA 402 map whose PDOs fit a CAN frame; pysoem's ``sdo_read`` over veth on our EtherCAT emulator, for
every shipped CiA 402 map (every axis of a multi-axis device). canopen's own waits are wall-clock
(python-can's virtual bus is threads): the checks are on positions and object values, with waits of
seconds for what takes tens of milliseconds.
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

import fieldbus
from fieldbus.core.pdo.model import DriveMap
from sim_slaves.od import is_cia402_drive

can = pytest.importorskip("can")
canopen = pytest.importorskip("canopen")

from canopen.profiles.p402 import BaseNode402  # noqa: E402

from sim_slaves.canopen import CanopenSimulator  # noqa: E402
from sim_slaves.canopen.eds import to_canopen_od  # noqa: E402

pytestmark = pytest.mark.timeout(180)
CYCLE_S = 0.005
CAN_FRAME_BYTES = 8
_channels = itertools.count()


def _cia402_maps() -> list[Path]:
    return [
        f for f in sorted(fieldbus.PDO_MAPS.glob("*.yaml")) if is_cia402_drive(fieldbus.load_drive_map(f))
    ]


def _fits_can(drive: DriveMap) -> bool:
    return all(
        sum(c.type.bits for c in p.channels) <= 8 * CAN_FRAME_BYTES for p in (*drive.rpdo, *drive.tpdo)
    )


CIA402_MAPS = _cia402_maps()
CAN_MAPS = [f for f in CIA402_MAPS if _fits_can(fieldbus.load_drive_map(f))]


def test_the_shipped_map_sets_are_the_ones_named() -> None:
    names = {f.stem for f in CIA402_MAPS}
    assert {"generic_cia402", "generic_cia402_2axis", "maxon_epos4", "elmo_gold"} <= names
    assert {"generic_cia402", "maxon_epos4_canopen"} <= {f.stem for f in CAN_MAPS}
    assert not any(fieldbus.load_drive_map(f).homing for f in CIA402_MAPS)  # "as it is": no homing section


def _wait(what: Callable[[], bool], timeout_s: float = 10.0) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if what():
            return True
        time.sleep(0.002)
    return False


def _position(node: Any) -> int:
    if 0x6064 in node.tpdo_values:
        return int(node.tpdo_values[0x6064])
    return int(node.sdo[0x6064].raw)


def _set_target(node: Any, counts: int) -> None:
    if 0x607A in node.rpdo_pointers:
        node.rpdo_pointers[0x607A].raw = counts
    else:
        node.sdo[0x607A].raw = counts


@pytest.mark.parametrize("map_file", CAN_MAPS, ids=lambda f: f.stem)
@pytest.mark.parametrize("method", [35, 37])
def test_canopen_base_node_402_homes_and_runs_pp_on_an_emulator_from_a_shipped_map(
    map_file: Path, method: int
) -> None:
    drive = fieldbus.load_drive_map(map_file)
    offset = 12_345 if method == 37 else -4_321  # counts: the position the home point reads
    target = 30_000  # counts from the home point
    channel = f"fb-shipped-oracle-{next(_channels)}-{time.monotonic_ns()}"
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
            node.nmt.state = "PRE-OPERATIONAL"
            for sdo in drive.sdo:  # the map's start-up writes, as canopen's user would make them
                node.sdo.download(sdo.index, sdo.sub_index, sdo.data)
            # the homing and profile objects exist with the device's defaults (0x06020000 before)
            assert node.sdo[0x6098].raw == 37
            assert node.sdo[0x607C].raw == 0
            assert node.sdo[0x6099][1].raw > 0 and node.sdo[0x6099][2].raw > 0
            assert node.sdo[0x609A].raw > 0
            for index in (0x6081, 0x6083, 0x6084):
                assert node.sdo[index].raw > 0, hex(index)
            node.sdo[0x6098].raw = method
            node.sdo[0x607C].raw = offset
            node.setup_402_state_machine(read_pdos=True)
            node.nmt.state = "OPERATIONAL"
            network.sync.start(CYCLE_S)
            for rpdo in node.rpdo.values():
                if rpdo.enabled:
                    rpdo.start(CYCLE_S)
            node.op_mode = "CYCLIC SYNCHRONOUS POSITION"
            assert node.homing(timeout=10) is True
            assert node.op_mode == "HOMING"
            assert _wait(lambda: _position(node) == offset), _position(node)
            # PP from the home point, through canopen's API (homing() left bit 4 up: drop it first, so
            # the set-point below is a rising edge)
            node.controlword = 0x000F
            _set_target(node, offset + target)
            node.op_mode = "PROFILED POSITION"
            assert node.op_mode == "PROFILED POSITION"
            assert node.state == "OPERATION ENABLED"
            node.controlword = 0x001F  # enable operation + bit 4 new set-point (absolute, single)
            assert _wait(lambda: node.statusword & 0x1000 != 0), "no set-point acknowledge (bit 12)"
            node.controlword = 0x000F
            assert _wait(lambda: node.statusword & 0x1400 == 0x0400), "no target reached (bit 10)"
            reached = int(node.sdo[0x6064].raw)
            window = int(node.sdo[0x6067].raw)
            assert node.state == "OPERATION ENABLED"
            network.sync.stop()
        finally:
            network.disconnect()
    assert not sim.errors
    assert abs(reached - (offset + target)) <= window, (reached, offset + target, window)


@pytest.mark.veth
@pytest.mark.usefixtures("generous_pysoem_timeouts")
def test_pysoem_reads_the_homing_and_profile_objects_of_every_shipped_cia402_map(
    ethercat_emulator: Any,
) -> None:
    pysoem = pytest.importorskip("pysoem")
    drives = [fieldbus.load_drive_map(f) for f in CIA402_MAPS]
    emu = ethercat_emulator(CIA402_MAPS)
    master = pysoem.Master()
    master.open(emu.iface)
    try:
        assert master.config_init() == len(drives)
        read = 0
        for slave, drive in zip(master.slaves, drives, strict=True):
            for off in drive.object_offsets:  # every axis of a multi-axis device
                method = int.from_bytes(slave.sdo_read(0x6098 + off, 0), "little", signed=True)
                home = int.from_bytes(slave.sdo_read(0x607C + off, 0), "little", signed=True)
                velocity = int.from_bytes(slave.sdo_read(0x6081 + off, 0), "little")
                speeds = [int.from_bytes(slave.sdo_read(0x6099 + off, s), "little") for s in (1, 2)]
                assert (method, home) == (37, 0), (drive.name, off)
                assert velocity > 0 and min(speeds) > 0, (drive.name, off)
                read += 1
        assert read == sum(d.axes for d in drives) >= len(CIA402_MAPS) + 1
    finally:
        master.close()
