"""Bus logs: CAN frames in python-can's formats (backends and emulators), `fieldbus decode`, EtherCAT pcap.

CAN runs on python-can's virtual bus with the real CANopen backend and emulator;
the pcap test runs the real pysoem master against the emulator over veth and
decodes the file with tshark.
"""

from __future__ import annotations

import errno
import itertools
import json
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

can = pytest.importorskip("can")

from fieldbus.cli import main  # noqa: E402
from fieldbus.commands.demo import DEMO_MAP  # noqa: E402
from fieldbus.core.pdo import load_drive_map  # noqa: E402
from fieldbus.errors import FieldbusError  # noqa: E402
from fieldbus.network import open_network  # noqa: E402
from fieldbus.platform.allocs import net_blocks  # noqa: E402
from fieldbus.wire.canlog import CanLogWriter, FrameRing  # noqa: E402
from sim_slaves.canopen import CanopenSimulator  # noqa: E402
from sim_slaves.ethercat.veth import VethUnavailable, delete_link, make_veth_pair  # noqa: E402

pytestmark = pytest.mark.timeout(120)
_channels = itertools.count()
NODES = 3
CYCLES = 200
EMCY_CODE = 0x2310  # CiA 301: continuous over-current


@pytest.fixture
def channel() -> str:
    return f"fb-buslog-{next(_channels)}-{time.monotonic_ns()}"


def _net(tmp_path: Path, channel: str) -> Path:
    f = tmp_path / "net.yaml"
    f.write_text(
        "cycle_time_us: 5000\nreceive_timeout_us: 20000\nsafe_stop_after: 1000\nbuses:\n"
        f"  - {{name: bus, type: canopen, interface: {channel}, can_interface: virtual,\n"
        f"     slaves: [{{name: 'j{{i}}', map: {json.dumps(str(DEMO_MAP))}, node_id: 1, count: {NODES}}}]}}\n"
    )
    return f


@pytest.fixture
def nodes(channel: str, tmp_path: Path) -> Iterator[CanopenSimulator]:
    drive = load_drive_map(DEMO_MAP)
    with (
        can.Bus(interface="virtual", channel=channel) as bus,
        CanopenSimulator(
            bus, [(drive, n) for n in range(1, NODES + 1)], dt_s=0.005, log=tmp_path / "emu.asc"
        ) as sim,
    ):
        yield sim


def _run_logged(tmp_path: Path, channel: str, nodes: CanopenSimulator, log: Path) -> dict[str, float]:
    """CYCLES cycles with the log on, an EMCY from node 2 half way; the master's last positions."""
    with open_network(_net(tmp_path, channel), can_log=str(log)) as net:
        op = net.bring_up()
        for k in range(CYCLES):
            if k == CYCLES // 2:
                nodes.send_emergency(2, EMCY_CODE)
            op.exchange()
        group = op[next(iter(op))]
        last = {f"j{i}": float(group.inputs["position_actual_value"][i]) for i in range(NODES)}
    return last


def test_candump_log_decodes_per_node_with_values_the_master_read(
    nodes: CanopenSimulator, channel: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    log = tmp_path / "bus.log"
    last = _run_logged(tmp_path, channel, nodes, log)
    frames = list(can.LogReader(str(log)))
    tx = [m for m in frames if not m.is_rx]
    syncs = [m for m in tx if m.arbitration_id == 0x080]
    assert len(syncs) >= CYCLES  # every cycle's SYNC was logged
    assert sum(1 for m in tx if m.arbitration_id == 0x201) >= CYCLES  # node 1's RPDO1 every cycle
    assert main(["decode", str(log), "--network", str(_net(tmp_path, channel)), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["frames"] == len(frames)
    rows = out["decoded"]
    by_kind = {r["kind"] for r in rows}
    assert {"nmt", "sync", "sdo", "rpdo", "tpdo", "heartbeat", "emcy"} <= by_kind
    emcy = [r for r in rows if r["kind"] == "emcy"]
    assert emcy and emcy[0]["node"] == 2 and "over-current" in emcy[0]["text"]
    # the identity read at bring-up, by SDO, decoded as a read and its answer
    assert any(r["text"] == "SDO request: read 0x1018:01" for r in rows)
    # each node's last TPDO1 in the log holds the position the master read in its last cycle
    for i in range(NODES):
        tpdo1 = [
            r for r in rows if r["kind"] == "tpdo" and r["node"] == i + 1 and r["text"].startswith("TPDO1")
        ]
        assert tpdo1, i
        assert tpdo1[-1]["values"]["position_actual_value"] == pytest.approx(last[f"j{i}"], abs=1e-9)


def test_the_same_frames_in_asc_and_blf_and_the_emulator_logs_its_side(
    nodes: CanopenSimulator, channel: str, tmp_path: Path
) -> None:
    counts = {}
    for suffix in (".asc", ".blf"):
        log = tmp_path / f"bus{suffix}"
        _run_logged(tmp_path, channel, nodes, log)
        frames = list(can.LogReader(str(log)))
        counts[suffix] = sum(1 for m in frames if m.arbitration_id == 0x080 and not m.is_rx)
        assert counts[suffix] >= CYCLES, suffix
        assert any(m.arbitration_id == 0x181 and m.is_rx for m in frames), suffix
    nodes.stop()  # the emulator's log is complete once it stops
    emu = list(can.LogReader(str(tmp_path / "emu.asc")))
    assert (
        sum(1 for m in emu if m.arbitration_id == 0x080 and m.is_rx) >= 2 * CYCLES
    )  # it saw both runs' SYNCs
    assert any(m.arbitration_id == 0x181 and not m.is_rx for m in emu)  # and sent TPDOs


def test_an_unwritable_log_fails_before_the_bus_starts(channel: str, tmp_path: Path) -> None:
    with pytest.raises(FieldbusError, match="cannot write"):
        open_network(_net(tmp_path, channel), can_log=str(tmp_path / "no" / "such" / "dir.log"))
    with pytest.raises(FieldbusError, match="unknown format"):
        open_network(_net(tmp_path, channel), can_log=str(tmp_path / "bus.pcapng"))


def test_a_full_disk_stops_the_log_with_a_warning_and_the_cycle_goes_on(
    nodes: CanopenSimulator, channel: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with open_network(_net(tmp_path, channel), can_log=str(tmp_path / "bus.log")) as net:
        log = net.backends[0]._log  # type: ignore[attr-defined]

        def full(_msg: Any) -> None:
            raise OSError(errno.ENOSPC, "No space left on device")

        log._out.on_message_received = full
        op = net.bring_up()
        fresh = sum(op.exchange().fresh for _ in range(50))
        time.sleep(0.2)  # the writer thread meets the full disk
        assert fresh >= 45
        assert log.error is not None and "No space left" in log.error
    assert "warning: CAN log" in capsys.readouterr().err


def test_decode_names_the_malformed_line(
    tmp_path: Path, channel: str, capsys: pytest.CaptureFixture[str]
) -> None:
    log = tmp_path / "bad.log"
    log.write_text("(1.000000) can0 080#\n(1.001000) can0 181#5002000000000000\n(1.002000) can0 18Z#zz\n")
    assert main(["decode", str(log), "--network", str(_net(tmp_path, channel))]) == 1
    assert f"{log}:3: malformed log entry" in capsys.readouterr().err


def test_a_full_ring_drops_and_counts_and_putting_allocates_nothing() -> None:
    ring = FrameRing(capacity=4)
    msg = can.Message(arbitration_id=0x181, data=bytes(8), is_extended_id=False)
    for _ in range(6):
        ring.put(msg, rx=True)
    assert (ring.head, ring.dropped) == (4, 2)
    ring = FrameRing(capacity=1 << 12)

    def put() -> None:
        ring.put(msg, rx=False, t=1.0)
        ring.tail = ring.head  # as if the writer kept up

    assert net_blocks(put, cycles=5000) <= 2


def test_writer_turns_ring_frames_into_the_same_frames(tmp_path: Path) -> None:
    ring = FrameRing(capacity=16)
    sent = [
        can.Message(timestamp=10.0 + i, arbitration_id=0x600 + i, data=bytes([i] * i), is_extended_id=False)
        for i in range(1, 9)
    ]
    for m in sent:
        ring.put(m, rx=bool(m.arbitration_id & 1))
    writer = CanLogWriter(tmp_path / "x.log", ring)
    writer.close()
    back = list(can.LogReader(str(tmp_path / "x.log")))
    assert [(m.arbitration_id, bytes(m.data), m.is_rx) for m in back] == [
        (m.arbitration_id, bytes(m.data), bool(m.arbitration_id & 1)) for m in sent
    ]
    assert [m.timestamp for m in back] == pytest.approx([m.timestamp for m in sent])


def test_ethercat_pcap_of_the_master_decodes_in_tshark(
    ethercat_emulator: Any, tmp_path: Path, tshark: Callable[[Path, str], int]
) -> None:
    emu = ethercat_emulator([DEMO_MAP], count=2)
    net_file = tmp_path / "net.yaml"
    net_file.write_text(
        "cycle_time_us: 1000\nreceive_timeout_us: 2000\nbuses:\n"
        f"  - {{name: bus, type: ethercat, interface: {emu.iface}, slaves: [{{name: 'j{{i}}', map: '{DEMO_MAP}', count: 2}}]}}\n"
    )
    pcap = tmp_path / "master.pcap"
    with open_network(net_file, pcap=str(pcap)) as net:
        op = net.bring_up()
        for _ in range(CYCLES):
            op.exchange()
        capture = net.backends[0].capture  # type: ignore[attr-defined]
    assert capture.error is None

    assert tshark(pcap, "_ws.malformed || _ws.expert.severity >= error") == 0
    assert tshark(pcap, "ecat.cmd == 12") >= 2 * CYCLES  # LRW: every cycle's request and its reply
    assert tshark(pcap, "ecat_mailbox.coe") > 0  # the bring-up's SDOs are in it too


@pytest.fixture
def private_link() -> Iterator[tuple[str, str]]:
    """A veth pair of this test's own, (captured end, sending end): other jobs on the machine that send
    EtherCAT frames on lo cannot add frames to a capture that counts them. Skips only when the
    machine refuses a pair, with its reason."""
    try:
        captured, sending = make_veth_pair()
    except VethUnavailable as exc:
        pytest.skip(str(exc))
    try:
        yield captured, sending
    finally:
        delete_link(captured)


def test_a_capture_closed_right_after_the_last_frames_keeps_them(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    tshark: Callable[[Path, str], int],
    private_link: tuple[str, str],
) -> None:
    """Frames already on the card when the bus closes are in the pcap: the capture thread, behind by many
    frames (a loaded machine, here a writer that takes 2 ms per frame), reads its socket empty first."""
    import socket

    from fieldbus.wire import pcap as wire_pcap

    captured, sending = private_link
    sender = socket.socket(socket.AF_PACKET, socket.SOCK_RAW)
    sender.bind((sending, 0))
    write = wire_pcap.PcapWriter.write

    def slow_write(self: Any, frame: Any, t_s: float) -> None:
        time.sleep(0.002)
        write(self, frame, t_s)

    monkeypatch.setattr(wire_pcap.PcapWriter, "write", slow_write)
    pcap = tmp_path / "close.pcap"
    capture = wire_pcap.EthercatCapture(pcap, captured)
    capture.start()
    # an EtherCAT frame (EtherType 0x88A4) with one BRD datagram, 50 times
    frame = bytes(6) + bytes.fromhex("020000000001") + b"\x88\xa4" + bytes.fromhex("0e10")
    frame += bytes([7, 0]) + bytes(4) + bytes.fromhex("0200") + bytes(2) + bytes(2) + bytes(2)
    with sender:
        for _ in range(50):
            sender.send(frame)
    capture.close()
    assert capture.error is None
    assert capture.frames == 50, capture.frames
    assert tshark(pcap, "ecat") == 50


def test_frames_the_kernel_dropped_are_counted_and_named(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, private_link: tuple[str, str]
) -> None:
    """A capture thread far behind a socket buffer too small for the burst: the kernel drops frames; the
    capture says how many (PACKET_STATISTICS) instead of leaving a file that silently lacks them."""
    import socket

    from fieldbus.wire import pcap as wire_pcap

    captured, sending = private_link
    sender = socket.socket(socket.AF_PACKET, socket.SOCK_RAW)
    sender.bind((sending, 0))
    write = wire_pcap.PcapWriter.write

    def slow_write(self: Any, frame: Any, t_s: float) -> None:
        time.sleep(0.002)
        write(self, frame, t_s)

    monkeypatch.setattr(wire_pcap.PcapWriter, "write", slow_write)
    monkeypatch.setattr(wire_pcap, "CAPTURE_BUFFER", 0)  # the kernel's least: a few frames
    capture = wire_pcap.EthercatCapture(tmp_path / "drops.pcap", captured)
    capture.start()
    frame = bytes(6) + bytes.fromhex("020000000001") + b"\x88\xa4" + bytes.fromhex("0e10")
    frame += bytes([7, 0]) + bytes(4) + bytes.fromhex("0200") + bytes(2) + bytes(2) + bytes(2)
    with sender:
        for _ in range(300):
            sender.send(frame)
    capture.close()
    assert capture.dropped > 0 and capture.frames + capture.dropped == 300, (capture.frames, capture.dropped)
    assert capture.error is not None and f"dropped {capture.dropped} frames" in capture.error
