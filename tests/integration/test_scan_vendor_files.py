"""Emulators built from vendor files, scanned: the scan gives back what the file says.

EtherCAT: the emulator (over veth, the real pysoem master scanning) is built from two
real ESI files (tests/data/esi): rt-labs' EVB-LAN9252 digital I/O (CoE, bit entries)
and one AB&T EasyCAT device (no mailbox: the scan reads its PDOs from the SII).
CANopen: the emulated node is built from canopen's sample EDS (tests/data/eds) and
scanned on python-can's virtual bus.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import pytest

from fieldbus.cli import main
from fieldbus.core.network import load_network
from fieldbus.core.pdo.model import DriveMap
from fieldbus.interop.device import load_device

DATA = Path(__file__).resolve().parents[1] / "data"
EVB9252 = str(DATA / "esi" / "rtlabs_evb9252_dig.xml")
EASYCAT = str(DATA / "esi" / "abt_easycat_v2_0.xml") + "#EasyCAT 16+16 rev 1"
SAMPLE_EDS = str(DATA / "eds" / "canopen_sample.eds")


def _entries(drive: DriveMap) -> dict[str, list[tuple[int, list[tuple[int, int, int]]]]]:
    """Per direction, each PDO's index and its entries (index, sub-index, bits), padding included."""
    return {
        key: [(p.index, [(c.index, c.sub_index, c.bits) for c in p.channels]) for p in pdos]
        for key, pdos in (("rpdo", drive.rpdo), ("tpdo", drive.tpdo))
    }


def _scanned(dev: dict[str, Any]) -> dict[str, list[tuple[int, list[tuple[int, int, int]]]]]:
    return {
        key: [
            (p["index"], [(e["index"], e["sub_index"], e["bits"]) for e in p["entries"]])
            for p in dev[key]
            if p["entries"] and p.get("enabled") is not False
        ]
        for key in ("rpdo", "tpdo")
    }


@pytest.mark.veth
@pytest.mark.timeout(300)
@pytest.mark.usefixtures("generous_pysoem_timeouts")
def test_ethercat_emulator_from_esi_files_scans_as_the_files_say(
    ethercat_emulator: Any, capsys: pytest.CaptureFixture[str]
) -> None:
    emu = ethercat_emulator([EVB9252, EASYCAT], app="none")
    assert main(["scan", "ethercat", emu.iface, "--json"]) == 0
    slaves = json.loads(capsys.readouterr().out)["slaves"]
    assert len(slaves) == 2
    for s, spec in zip(slaves, (EVB9252, EASYCAT), strict=True):
        src = load_device(spec)
        ident = s["identity"]
        assert (ident["vendor_id"], ident["product_id"], ident["revision"]) == (
            src.vendor_id,
            src.product_id,
            src.revision,
        )
        assert _scanned(s) == _entries(src), spec
    assert slaves[0]["mailbox_protocols"] == ["CoE", "FoE"] and slaves[0]["mapping_source"] == "coe"
    assert slaves[1]["mailbox_protocols"] == [] and slaves[1]["mapping_source"] == "sii"


@pytest.mark.timeout(120)
def test_canopen_emulator_from_an_eds_scans_as_the_file_says(capsys: pytest.CaptureFixture[str]) -> None:
    can = pytest.importorskip("can")
    pytest.importorskip("canopen")
    from sim_slaves.canopen import CanopenSimulator

    src = load_device(SAMPLE_EDS)
    channel = f"fb-scan-eds-{time.monotonic_ns()}"
    with (
        can.Bus(interface="virtual", channel=channel) as bus,
        CanopenSimulator(bus, [(src, 2)], dt_s=0.005),
    ):
        assert main(["scan", "canopen", channel, "--interface", "virtual", "--listen", "0", "--json"]) == 0
    (node,) = json.loads(capsys.readouterr().out)["nodes"]
    assert node["node_id"] == 2
    assert (node["identity"]["vendor_id"], node["identity"]["product_id"]) == (src.vendor_id, src.product_id)
    assert _scanned(node) == _entries(src)


ORBITA = str(DATA / "esi" / "pollen_orbita2d.xml")


@pytest.mark.veth
@pytest.mark.timeout(300)
@pytest.mark.usefixtures("generous_pysoem_timeouts")
def test_a_fixed_assignment_servo_from_its_esi_scans_and_runs(
    ethercat_emulator: Any, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Orbita2d (CoE, DC, TxPDOs 0x1700/0x1800, no PdoAssign): the emulator built from the file has a
    read-only assignment and fixed mappings, so a bring-up that wrote either would abort."""
    emu = ethercat_emulator([ORBITA, ORBITA], app="none")
    assert main(["import", "esi", ORBITA, "-o", str(tmp_path / "orbita2d.yaml")]) == 0
    capsys.readouterr()
    net = tmp_path / "net.yaml"
    net.write_text(
        "cycle_time_us: 8000\nreceive_timeout_us: 6000\nbuses:\n"
        f"  - {{name: arm, type: ethercat, interface: {emu.iface}, "
        "slaves: [{name: 'o{i}', map: orbita2d.yaml, count: 2}]}\n"
    )
    code = main(["run", str(net), "--cycles", "200", "--json"])
    (b,) = json.loads(capsys.readouterr().out)["buses"]
    assert (b["expected_wkc"], b["short"]) == (6, 0)
    assert b["cycles"] - b["timeouts"] >= 100 and code in (0, 3)  # a user-space emulator: late now and then
    # the scan reads the device's own assignment (0x1C13 = 0x1700, 0x1800) and writes a map that runs too
    out_dir = tmp_path / "maps"
    args = ["--json", "--write-maps", str(out_dir), "--cycle-time-us", "8000", "--receive-timeout-us", "6000"]
    assert main(["scan", "ethercat", emu.iface, *args]) == 0
    slaves = json.loads(capsys.readouterr().out)["slaves"]
    src = load_device(ORBITA)
    assert all(_scanned(s) == _entries(src) for s in slaves)
    assert all(s["assign_fixed"] and all(p["fixed"] for p in s["rpdo"] + s["tpdo"]) for s in slaves)
    written = load_network(out_dir / "network.yaml").buses[0].slaves[0].map
    assert not written.ethercat.pdo_assign and all(p.fixed for p in (*written.rpdo, *written.tpdo))
    code = main(["run", str(out_dir / "network.yaml"), "--cycles", "200", "--json"])
    (b,) = json.loads(capsys.readouterr().out)["buses"]
    assert (b["expected_wkc"], b["short"]) == (6, 0) and b["cycles"] - b["timeouts"] >= 100 and code in (0, 3)
