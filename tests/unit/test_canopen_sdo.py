"""The emulated CANopen node's SDO server, frame by frame (CiA 301 7.2.4), hand-computed."""

from __future__ import annotations

from fieldbus.commands.demo import DEMO_MAP
from fieldbus.core.pdo import load_drive_map
from sim_slaves.canopen import CanopenNode, NmtState

H = bytes.fromhex


def _node() -> CanopenNode:
    node = CanopenNode(load_drive_map(DEMO_MAP), 5)
    assert node.boot() == [(0x705, b"\x00")]  # boot-up message
    assert node.state is NmtState.PRE_OPERATIONAL
    return node


def test_expedited_upload_of_the_vendor_id() -> None:
    assert _node().sdo(H("40 18 10 01 00 00 00 00")) == (0x585, H("43 18 10 01 B1 0F 00 00"))


def test_segmented_upload_of_the_device_name_with_toggle_bits() -> None:
    node = _node()
    assert node.sdo(H("40 08 10 00 00 00 00 00")) == (0x585, H("41 08 10 00 0A 00 00 00"))  # size 10
    assert node.sdo(H("60 00 00 00 00 00 00 00")) == (0x585, b"\x00demo_jo")  # toggle 0, 7 bytes, more
    # toggle 1, n = 4 unused bytes, c = 1 last: 0x10 | 4 << 1 | 1 = 0x19
    assert node.sdo(H("70 00 00 00 00 00 00 00")) == (0x585, b"\x19int\x00\x00\x00\x00")


def test_a_wrong_toggle_bit_aborts_with_05030000() -> None:
    node = _node()
    node.sdo(H("40 08 10 00 00 00 00 00"))
    assert node.sdo(H("70 00 00 00 00 00 00 00")) == (0x585, H("80 08 10 00 00 00 03 05"))


def test_expedited_download_and_abort_codes() -> None:
    node = _node()
    assert node.sdo(H("2F 60 60 00 0A 00 00 00")) == (0x585, H("60 60 60 00 00 00 00 00"))  # CST
    assert node.od.get_value(0x6060, 0) == 10
    # no such object: 0x06020000
    assert node.sdo(H("40 77 77 00 00 00 00 00")) == (0x585, H("80 77 77 00 00 00 02 06"))
    # read-only identity: 0x06010002
    assert node.sdo(H("23 18 10 01 01 00 00 00")) == (0x585, H("80 18 10 01 02 00 01 06"))


def test_mapping_changes_only_with_the_pdo_invalid() -> None:
    node = _node()
    # TPDO2 (0x1A01) is valid: its mapping cannot change (0x08000022)
    assert node.sdo(H("2F 01 1A 00 00 00 00 00")) == (0x585, H("80 01 1A 00 22 00 00 08"))
    # COB-ID 0x285 with bit 31 set, then the mapping may change
    assert node.sdo(H("23 01 18 01 85 02 00 80"))[1][0] == 0x60
    assert node.sdo(H("2F 01 1A 00 00 00 00 00"))[1][0] == 0x60
    assert node.sdo(H("23 01 1A 01 10 00 77 60"))[1][0] == 0x60  # 0x6077:00, 16 bits
    assert node.sdo(H("2F 01 1A 00 01 00 00 00"))[1][0] == 0x60
    assert node.sdo(H("23 01 18 01 85 02 00 00"))[1][0] == 0x60  # valid again
    node.nmt(0x01)
    node.od.set_value(0x6077, 0, -5)
    frames = dict(node.sync(0.001))
    assert frames[0x285] == H("FB FF")  # TPDO2 now carries only the torque: 2 bytes


def test_segmented_download_of_a_string() -> None:
    node = _node()
    node.od.add(0x2000, 0, None, b"x" * 10, name="a writable string")
    assert node.sdo(H("21 00 20 00 0A 00 00 00")) == (0x585, H("60 00 20 00 00 00 00 00"))
    assert node.sdo(b"\x00abcdefg") == (0x585, H("20 00 00 00 00 00 00 00"))
    # toggle 1, 4 unused, last
    assert node.sdo(b"\x19hij\x00\x00\x00\x00") == (0x585, H("30 00 00 00 00 00 00 00"))
    assert node.od.read(0x2000, 0) == b"abcdefghij"
