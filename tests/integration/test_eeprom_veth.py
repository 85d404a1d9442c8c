"""``fieldbus eeprom`` and ``fieldbus scan ethercat --errors`` with the real pysoem master over veth.

Oracles: pysoem's own EEPROM calls (SOEM's ecx_readeepromFP / ecx_writeeepromFP, an
independent implementation of the EEPROM interface sequence) read what our
command wrote, and write what our command then reads; the emulator's own
EEPROM bytes (its control socket) are compared too. The ESC behaviour at power-up
(checksum, alias) is our emulator's, written from the ESC datasheet.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from fieldbus.cli import main
from fieldbus.core import sii

REPO = Path(__file__).resolve().parents[2]
GENERIC = REPO / "fieldbus" / "pdo_maps" / "generic_cia402.yaml"
DEMO_JOINT = REPO / "fieldbus" / "data" / "demo_joint.yaml"


def _run(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str, str]:
    capsys.readouterr()
    code = main(list(args))
    out, err = capsys.readouterr()
    return code, out, err


def _pysoem_master(iface: str) -> Any:
    import pysoem

    m = pysoem.Master()
    m.open(iface)
    assert m.config_init() > 0
    return m


@pytest.mark.veth
@pytest.mark.timeout(300)
@pytest.mark.usefixtures("generous_pysoem_timeouts")
def test_alias_written_survives_a_power_cycle_and_pysoem_agrees(
    ethercat_emulator: Any, tmp_path: Path, capsys: pytest.CaptureFixture[str], tshark: Any
) -> None:
    pcap = tmp_path / "eeprom.pcap"
    emu = ethercat_emulator([GENERIC], count=3, app="none", pcap=pcap)
    code, out, err = _run(capsys, "eeprom", "alias", emu.iface, "1", "0x0BEE")
    assert code == 0, err
    assert "words written and read back" in out
    assert emu.command(cmd="sii", slave=1)["alias"] == 0  # not before the power-up
    emu.command(cmd="power_cycle", slave=1)
    assert emu.command(cmd="sii", slave=1)["alias"] == 0x0BEE
    # the oracle: SOEM reads the alias register and the EEPROM word
    m = _pysoem_master(emu.iface)
    try:
        s = m.slaves[1]
        assert int.from_bytes(bytes(s._fprd(0x0012, 2)), "little") == 0x0BEE
        assert int.from_bytes(bytes(s.eeprom_read(4))[:2], "little") == 0x0BEE
        # and pysoem's own write, read back by our command
        s.eeprom_write(4, (0x0123).to_bytes(2, "little"))
    finally:
        m.close()
    out_file = tmp_path / "s1.bin"
    code, out, err = _run(capsys, "eeprom", "read", emu.iface, "1", "-o", str(out_file), "--json")
    assert code == 0, err
    doc = json.loads(out)
    assert doc["alias"] == 0x0123 and not doc["checksum_ok"]  # pysoem wrote word 4 without the checksum
    image = out_file.read_bytes()
    assert image == bytes.fromhex(emu.command(cmd="sii", slave=1)["sii"])[: len(image)]
    # decode offline
    code, out, _ = _run(capsys, "eeprom", "decode", str(out_file))
    assert code == 0 and "WRONG" in out
    # tshark: the EEPROM interface accesses decode, none malformed; our write commands are there
    emu.stop()
    assert tshark(pcap, "_ws.malformed || _ws.expert.severity >= error") == 0
    assert tshark(pcap, "ecat.ado == 0x0502 && ecat.cmd == 5") >= 4  # FPWR of EEPROM control
    assert tshark(pcap, "ecat.ado == 0x0508 && ecat.cmd == 5") >= 2  # FPWR of the data word


@pytest.mark.veth
@pytest.mark.timeout(300)
@pytest.mark.usefixtures("generous_pysoem_timeouts")
def test_a_wrong_checksum_is_reported_after_power_up_and_write_repairs_it(
    ethercat_emulator: Any, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    emu = ethercat_emulator([GENERIC], count=2, app="none")
    good = bytes.fromhex(emu.command(cmd="sii", slave=0)["sii"])
    m = _pysoem_master(emu.iface)
    try:  # a bad checksum written with pysoem's own call (the alias word, CRC untouched)
        m.slaves[0].eeprom_write(4, (77).to_bytes(2, "little"))
    finally:
        m.close()
    emu.command(cmd="power_cycle", slave=0)
    assert not emu.command(cmd="sii", slave=0)["loaded"]
    code, out, err = _run(capsys, "scan", "ethercat", emu.iface, "--errors", "--json")
    assert code == 0, err
    s0 = json.loads(out)["slaves"][0]
    assert s0["eeprom_checksum_error"] and s0["pdi_operational"] is False
    assert "checksum error" in s0["eeprom"]
    # an image for another product is refused without --force
    other = bytearray(good)
    other[0x14:0x18] = (0x12345678).to_bytes(4, "little")
    f = tmp_path / "other.bin"
    f.write_bytes(bytes(other))
    code, _, err = _run(capsys, "eeprom", "write", emu.iface, "0", str(f))
    assert code == 1 and "--force" in err
    # the good image back: only the differing words, checksum recomputed, loaded at the next power-up
    g = tmp_path / "good.bin"
    g.write_bytes(good)
    code, out, err = _run(capsys, "eeprom", "write", emu.iface, "0", str(g))
    assert code == 0, err
    emu.command(cmd="power_cycle", slave=0)
    st = emu.command(cmd="sii", slave=0)
    assert st["loaded"] and bytes.fromhex(st["sii"])[:16] == sii.with_checksum(good)[:16]
    # single words: one outside the configuration area, one inside it (its checksum follows)
    code, out, err = _run(capsys, "eeprom", "word", emu.iface, "0", "0x0E", "4321")
    assert code == 0 and "1 word(s)" in out, err
    code, out, err = _run(capsys, "eeprom", "word", emu.iface, "0", "4", "9")
    assert code == 0 and "2 word(s)" in out, err
    emu.command(cmd="power_cycle", slave=0)
    st = emu.command(cmd="sii", slave=0)
    assert st["loaded"] and st["alias"] == 9
    m = _pysoem_master(emu.iface)
    try:
        assert int.from_bytes(bytes(m.slaves[0].eeprom_read(0x0E))[:2], "little") == 4321
    finally:
        m.close()


@pytest.mark.veth
@pytest.mark.timeout(300)
@pytest.mark.usefixtures("generous_pysoem_timeouts")
def test_scan_errors_names_the_cable_with_bit_errors_and_reset_clears(
    ethercat_emulator: Any, capsys: pytest.CaptureFixture[str]
) -> None:
    emu = ethercat_emulator([GENERIC], count=12, app="none")
    m = _pysoem_master(emu.iface)  # config_init clears 0x0300-0x0307: errors injected after it
    emu.command(cmd="bit_errors", slave=4, rate=1.0, seed=3, frames=40)
    try:
        lost = 0
        for _ in range(60):
            try:
                m.slaves[0]._fprd(0x0130, 2, 2000)
            except Exception:
                lost += 1
        assert lost >= 1
    finally:
        m.close()
    code, out, err = _run(capsys, "scan", "ethercat", emu.iface, "--errors", "--json")
    assert code == 0, err
    doc = json.loads(out)
    assert doc["suspects"][0]["upstream"] == 4 and doc["suspects"][0]["downstream"] == 5, doc["suspects"]
    assert len(doc["suspects"]) == 1
    assert (
        doc["slaves"][5]["ports"][0]["invalid_frame"] > 0 or doc["slaves"][4]["ports"][1]["invalid_frame"] > 0
    )
    code, out, err = _run(capsys, "scan", "ethercat", emu.iface, "--errors", "--reset-errors")
    assert code == 0 and "cable between slave 4 port 1 and slave 5 port 0" in out, out + err
    code, out, _ = _run(capsys, "scan", "ethercat", emu.iface, "--errors", "--json")
    assert code == 0 and json.loads(out)["suspects"] == []


@pytest.mark.veth
@pytest.mark.timeout(600)
def test_in_op_with_pysoem_the_watch_names_the_cable(tmp_path: Path) -> None:
    """The real pysoem backend in OP over veth, error_counters on: its reads go beside SOEM's LRW on
    SOEM's socket; bit errors between slaves 4 and 5 of 12 (the emulator's fault model)."""
    from fieldbus.testing import EmulationUnavailable, emulate

    net = tmp_path / "line.yaml"
    net.write_text(
        "cycle_time_us: 2000\nreceive_timeout_us: 20000\nbuses:\n"
        f"  - {{name: arm, type: ethercat, interface: eth0, slaves: [{{name: 'j{{i}}', map: {json.dumps(str(GENERIC))}, count: 12}}]}}\n"
    )
    options = {"arm": {"error_counters": True}}
    try:
        with emulate(net, ethercat="veth", receive_timeout_us=20000, bus_options=options) as emu:
            _watch_names_the_cable(emu)
    except EmulationUnavailable as exc:
        pytest.skip(str(exc))


def _watch_names_the_cable(emu: Any) -> None:
    from fieldbus.core.esc_errors import Link

    op = emu.op
    for _ in range(60):  # every slave's baseline (24 free cycles a round)
        op.exchange()
    emu.bit_errors("arm", between=("j4", "j5"), rate=0.05, seed=2)
    events = []
    for _ in range(800):
        events += [e for e in op.exchange().events if e.kind == "esc_errors"]
    b = emu.network.backend("arm")
    watch = b.error_watch
    assert watch.suspects() and watch.suspects()[0].link == Link(4, 1, 5, 0), watch.suspects()
    named = [e for e in events if "suspect" in e.detail]
    assert named and all("slave 4 (j4) port 1 and slave 5 (j5) port 0" in e.detail for e in named)
    assert b.diag_datagrams <= 860
