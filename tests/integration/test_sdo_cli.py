"""``fieldbus sdo read|write|list`` on both buses: pysoem against the emulator over veth, and the CANopen
emulator on python-can's virtual bus. Typed values, strings in segmented transfers, aborts by name."""

from __future__ import annotations

import itertools
import json
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from fieldbus.cli import main
from fieldbus.core.pdo import load_drive_map

REPO = Path(__file__).resolve().parents[2]
GENERIC = REPO / "fieldbus" / "pdo_maps" / "generic_cia402.yaml"
LONG_NAME = "long_" * 30 + "drive"  # 155 bytes: more than one 128-byte mailbox (CoE) or 4 bytes (CAN) holds
_channels = itertools.count()


def _long_map(tmp_path: Path) -> Path:
    path = tmp_path / "long.yaml"
    # another product code too: SOEM copies the SII of a slave with the same identity as an earlier one
    text = GENERIC.read_text().replace("name: generic_cia402", f"name: {LONG_NAME}")
    path.write_text(text.replace("product_id: 0x00000402", "product_id: 0x00000403"))
    return path


def _run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.mark.veth
@pytest.mark.timeout(300)
@pytest.mark.usefixtures("generous_pysoem_timeouts")
def test_sdo_on_ethercat(ethercat_emulator: Any, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    emu = ethercat_emulator([_long_map(tmp_path), GENERIC], app="none")
    bus = ("ethercat", emu.iface)

    # a string in a segmented CoE upload, typed by the slave's SDO Information
    code, out, _ = _run(capsys, "sdo", "read", *bus, "--slave", "0", "0x1008", "0", "--json")
    assert code == 0
    r = json.loads(out)
    assert (r["type"], r["value"], r["bytes"]) == ("string", LONG_NAME, len(LONG_NAME))

    # write typed from --type, read back typed from SDO Information
    code, out, _ = _run(capsys, "sdo", "write", *bus, "--slave", "1", "0x6060", "0", "-3", "--type", "int8")
    assert code == 0 and "slave 1 (generic_cia402) 0x6060:00 <- -3 [int8, 1 bytes]" in out
    code, out, _ = _run(capsys, "sdo", "read", *bus, "--slave", "1", "0x6060", "0")
    assert code == 0 and "0x6060:00 = -3 (0xFD)  [int8, 1 bytes]" in out
    # a string longer than the mailbox: a segmented CoE download, typed by SDO Information (no --type)
    code, out, _ = _run(capsys, "sdo", "write", *bus, "--slave", "1", "0x2100", "0", LONG_NAME[::-1])
    assert code == 0 and f"0x2100:00 <- {LONG_NAME[::-1]} [string, {len(LONG_NAME)} bytes]" in out
    code, out, _ = _run(capsys, "sdo", "read", *bus, "--slave", "1", "0x2100", "0", "--json")
    assert code == 0 and json.loads(out)["value"] == LONG_NAME[::-1]
    code, out, _ = _run(capsys, "sdo", "read", *bus, "--slave", "1", "0x1018", "2")
    assert code == 0 and "= 1026 (0x00000402)  [uint32, 4 bytes]" in out

    # aborts name slave, object, code and its meaning
    code, _, err = _run(capsys, "sdo", "read", *bus, "--slave", "1", "0x5555", "0")
    assert code == 1
    assert (
        "slave 1 (generic_cia402): SDO abort 0x06020000 'Object does not exist in the object dictionary'"
        in err
    )
    assert "0x5555:00" in err
    code, _, err = _run(capsys, "sdo", "write", *bus, "--slave", "0", "0x1018", "1", "7", "--type", "uint32")
    assert code == 1 and "0x06010002 'Attempt to write a read only object' on 0x1018:01" in err
    code, _, err = _run(capsys, "sdo", "write", *bus, "--slave", "0", "0x6060", "0", "300", "--type", "int8")
    assert code == 1 and "300 does not fit int8" in err
    code, _, err = _run(capsys, "sdo", "read", *bus, "--slave", "5", "0x1000", "0")
    assert code == 1 and "no slave at position 5: 2 slaves" in err

    # the object dictionary through SDO Information
    code, out, _ = _run(capsys, "sdo", "list", *bus, "--slave", "1")
    assert code == 0
    assert "0x6040  VAR    controlword  [uint16, 16 bit, rw,rxpdo]" in out
    assert "0x1018  RECORD Identity object  [IDENTITY]" in out
    assert "   :01  Vendor ID  [uint32, 32 bit, ro]" in out
    assert "0x1C12  ARRAY  RxPDO assign  [uint16]" in out
    code, out, _ = _run(capsys, "sdo", "list", *bus, "--slave", "1", "--json")
    objects = {o["index"]: o for o in json.loads(out)["objects"]}
    assert objects[0x6041]["access"] == "rw,txpdo"
    assert [e["name"] for e in objects[0x1A00]["entries"]][:2] == [
        "Highest sub-index supported",
        "SubIndex 001",
    ]


@pytest.fixture
def can_channel() -> str:
    return f"fb-sdo-{next(_channels)}-{time.monotonic_ns()}"


@pytest.fixture
def can_nodes(can_channel: str, tmp_path: Path) -> Iterator[Any]:
    can = pytest.importorskip("can")
    from sim_slaves.canopen import CanopenSimulator

    nodes = [(load_drive_map(_long_map(tmp_path)), 3), (load_drive_map(GENERIC), 4)]
    with can.Bus(interface="virtual", channel=can_channel) as bus, CanopenSimulator(bus, nodes) as sim:
        yield sim
    assert not sim.errors


@pytest.mark.timeout(60)
def test_sdo_on_canopen(can_nodes: Any, can_channel: str, capsys: pytest.CaptureFixture[str]) -> None:
    bus = ("canopen", can_channel, "--interface", "virtual")
    code, out, _ = _run(capsys, "sdo", "read", *bus, "--node", "3", "0x1008", "0", "--json")
    assert code == 0
    r = json.loads(out)
    assert (r["type"], r["value"], r["bytes"]) == ("string", LONG_NAME, len(LONG_NAME))  # 23 segments

    code, out, _ = _run(capsys, "sdo", "write", *bus, "--node", "4", "0x6060", "0", "9")  # int8 by CiA 402
    assert code == 0 and "node 4 0x6060:00 <- 9 [int8, 1 bytes]" in out
    assert can_nodes.node(4).od.get_value(0x6060, 0) == 9
    code, out, _ = _run(capsys, "sdo", "read", *bus, "--node", "4", "0x6060", "0")
    assert code == 0 and "node 4 0x6060:00 = 9 (0x09)  [int8, 1 bytes]" in out
    # a segmented download: 155 bytes in 23 segments, toggle bits checked by the node
    code, out, _ = _run(
        capsys, "sdo", "write", *bus, "--node", "4", "0x2100", "0", LONG_NAME, "--type", "string"
    )
    assert code == 0 and f"node 4 0x2100:00 <- {LONG_NAME} [string, {len(LONG_NAME)} bytes]" in out
    assert can_nodes.node(4).od.entry(0x2100, 0).value == LONG_NAME.encode()
    code, out, _ = _run(
        capsys, "sdo", "read", *bus, "--node", "4", "0x2100", "0", "--type", "string", "--json"
    )
    assert code == 0 and json.loads(out)["value"] == LONG_NAME
    code, out, _ = _run(capsys, "sdo", "read", *bus, "--node", "4", "0x1A00", "1", "--type", "uint32")
    assert code == 0 and "= 1614872592 (0x60410010)" in out

    code, _, err = _run(capsys, "sdo", "read", *bus, "--node", "4", "0x5555", "0")
    assert code == 1
    assert "node 4: SDO abort 0x06020000 'Object does not exist in the object dictionary' on 0x5555:00" in err
    code, _, err = _run(capsys, "sdo", "write", *bus, "--node", "4", "0x2000", "0", "1")
    assert code == 1 and "give --type" in err
    code, _, err = _run(capsys, "sdo", "read", *bus, "--node", "99", "0x1000", "0", "--timeout", "0.1")
    assert code == 1 and "node 99: no SDO answer within 100 ms" in err
    code, _, err = _run(capsys, "sdo", "list", *bus, "--node", "4")
    assert code == 1 and "no SDO Information" in err
