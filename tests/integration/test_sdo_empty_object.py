"""An SDO upload of an empty object: a normal (not expedited) upload response of size 0.

An expedited transfer carries 1-4 bytes (CiA 301 §7.2.4.3.6; ETG.1000.6 §5.6.2.4): its size
field ``n`` (bits 2-3) counts the unused of 4 bytes, so 0 bytes cannot be said; ``0x43 | 4 << 2``
spills into bit 4 (0x53, complete access on EtherCAT) and reads as 4 bytes. An empty object
(the emulators' default-empty 0x2100 "User label") answers 0x41 with size 0 instead: on
EtherCAT with no data after it, on CAN followed by one segment that carries no data.

Oracles: the real pysoem master over veth (SOEM's own SDO client) and canopen's RemoteNode on
python-can's virtual bus; the response bytes are also checked against the specification.
"""

from __future__ import annotations

import struct
import time
from pathlib import Path
from typing import Any

import pytest

from fieldbus import PDO_MAPS
from fieldbus.core.pdo import load_drive_map
from sim_slaves.ethercat.coe import CoeService, SdoServer
from sim_slaves.od import USER_LABEL, CommState, ObjectDictionary

GENERIC = PDO_MAPS / "generic_cia402.yaml"


def _coe_upload(index: int, sub: int) -> bytes:
    return struct.pack("<HBHBI", CoeService.SDO_REQUEST << 12, 0x40, index, sub, 0)


def test_coe_upload_response_bytes() -> None:
    od = ObjectDictionary.from_drive_map(load_drive_map(GENERIC))
    server = SdoServer(od, mailbox_in=128)
    for value, answer in (
        (b"", bytes([0x41, 0x00, 0x21, 0x00]) + bytes(4)),  # normal upload, size 0, no data after it
        (b"a", bytes([0x4F, 0x00, 0x21, 0x00]) + b"a\0\0\0"),  # expedited, 3 bytes unused
        (b"abcd", bytes([0x43, 0x00, 0x21, 0x00]) + b"abcd"),  # expedited, 0 unused
    ):
        od.write(USER_LABEL, 0, value, state=CommState.PRE_OPERATIONAL)
        coe = server.handle(_coe_upload(USER_LABEL, 0), CommState.PRE_OPERATIONAL)
        assert coe == struct.pack("<H", CoeService.SDO_RESPONSE << 12) + answer, value
        assert not coe[2] & 0x10  # never the complete-access bit


def test_canopen_upload_response_bytes() -> None:
    from sim_slaves.canopen import CanopenNode

    node = CanopenNode(load_drive_map(GENERIC), 5)
    assert node.sdo(bytes([0x40, 0x00, 0x21, 0x00]) + bytes(4)) == (
        0x585,
        bytes([0x41, 0, 0x21, 0]) + bytes(4),
    )
    # the one segment: toggle 0, n = 7 (no data byte used), c = 1 (last)
    assert node.sdo(bytes([0x60]) + bytes(7)) == (0x585, bytes([0x0F]) + bytes(7))


def test_canopen_remote_node_reads_the_empty_object() -> None:
    can = pytest.importorskip("can")
    canopen = pytest.importorskip("canopen")
    from sim_slaves.canopen import CanopenSimulator
    from sim_slaves.canopen.eds import to_canopen_od

    channel = f"fb-sdo-empty-{time.monotonic_ns()}"
    drive = load_drive_map(GENERIC)
    with can.Bus(interface="virtual", channel=channel) as bus, CanopenSimulator(bus, [(drive, 9)]) as sim:
        network = canopen.Network()
        network.connect(interface="virtual", channel=channel)
        try:
            node = canopen.RemoteNode(9, to_canopen_od(sim.node(9).od))
            network.add_node(node)
            assert node.sdo.upload(USER_LABEL, 0) == b""
            node.sdo.download(USER_LABEL, 0, b"left arm")  # segmented download, then upload
            assert node.sdo.upload(USER_LABEL, 0) == b"left arm"
            node.sdo.download(USER_LABEL, 0, b"ab")
            assert node.sdo.upload(USER_LABEL, 0) == b"ab"  # expedited, 2 bytes
        finally:
            network.disconnect()
        assert not sim.errors


@pytest.mark.veth
@pytest.mark.timeout(120)
@pytest.mark.usefixtures("generous_pysoem_timeouts")
def test_pysoem_reads_the_empty_object_as_no_bytes(ethercat_emulator: Any, tmp_path: Path) -> None:
    import pysoem

    emu = ethercat_emulator([GENERIC], app="none")
    master = pysoem.Master()
    master.open(emu.iface)
    try:
        assert master.config_init() == 1
        slave = master.slaves[0]
        assert slave.sdo_read(USER_LABEL, 0) == b""
        slave.sdo_write(USER_LABEL, 0, b"abc")
        assert slave.sdo_read(USER_LABEL, 0) == b"abc"
    finally:
        master.close()
