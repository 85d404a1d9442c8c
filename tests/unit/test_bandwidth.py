"""Bandwidth calculator: published figures, the seed's exercises, the CLI.

Sources of every figure are in docs/bandwidth.md; the test names say which.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from fieldbus.cli import main
from fieldbus.core.bandwidth import (
    CanFrame,
    CanOptions,
    CanParams,
    EcatSlave,
    EthercatParams,
    bus_bandwidth,
    can_cycle,
    can_fd_length,
    can_frame_bits,
    can_frame_time_us,
    can_response_times_us,
    ethercat_cycle,
    ethercat_frames,
    ethernet_wire_bytes,
    network_bandwidth,
    wire_time_us,
)
from fieldbus.core.pdo import drive_map_from_text
from fieldbus.core.pdo.model import DriveMap
from fieldbus.errors import PdoMapError

# ---------------------------------------------------------------- classic CAN


def test_davis_2007_standard_8_byte_frame() -> None:
    # Davis et al. 2007: 135 bits worst case incl. 3-bit IFS; 111 without stuffing.
    assert can_frame_bits(8) == 135
    assert can_frame_bits(8, worst_case=False) == 111


def test_davis_2007_extended_8_byte_frame() -> None:
    assert can_frame_bits(8, extended=True) == 160
    assert can_frame_bits(8, extended=True, worst_case=False) == 131


def test_sync_and_6_byte_frames() -> None:
    assert (can_frame_bits(0), can_frame_bits(0, worst_case=False)) == (55, 47)
    assert (can_frame_bits(6), can_frame_bits(6, worst_case=False)) == (115, 95)


def test_classic_can_rejects_9_bytes() -> None:
    with pytest.raises(ValueError, match=r"0\.\.8"):
        can_frame_bits(9)


@given(st.integers(0, 8), st.booleans())
def test_worst_case_is_nominal_plus_stuffing_bound(n: int, ext: bool) -> None:
    worst, nominal = can_frame_bits(n, extended=ext), can_frame_bits(n, extended=ext, worst_case=False)
    g = 54 if ext else 34
    assert worst - nominal == (g + 8 * n - 1) // 4
    assert nominal == g + 8 * n + 13


def _axes_frames(n_axes: int, sync: bool = True) -> list[CanFrame]:
    frames = [CanFrame(0x080, 0, "SYNC")] if sync else []
    frames += [CanFrame(0x200 + i, 8, f"RPDO{i}") for i in range(1, n_axes + 1)]
    frames += [CanFrame(0x180 + i, 8, f"TPDO{i}") for i in range(1, n_axes + 1)]
    return frames


def test_12_axes_on_one_classic_bus_is_about_300_hz() -> None:
    # can_facts.md: 12 x (RPDO + TPDO, 8 bytes) + SYNC = 3295 bits worst case.
    r = can_cycle(_axes_frames(12), CanParams(1_000_000), 1000.0)
    assert r.wire_bits_per_cycle == 3295
    assert r.wire_time_us == pytest.approx(3295.0)
    assert r.load_percent == pytest.approx(329.5)
    assert r.max_rate_hz == pytest.approx(1e6 / 3295)
    assert r.extra("schedulable") is False
    assert r.extra("worst_response_us") is None  # utilisation > 1: unbounded


def test_3_axes_per_bus_fit_1_khz_and_response_time() -> None:
    r = can_cycle(_axes_frames(3), CanParams(1_000_000), 1000.0)
    assert r.wire_time_us == pytest.approx(865.0)
    # Lowest priority (RPDO3, 0x203) waits for all 6 others, then goes: 865 µs.
    assert r.extra("worst_response_frame") == "RPDO3"
    assert r.extra("worst_response_us") == pytest.approx(865.0)
    assert r.extra("schedulable") is True


def test_response_time_counts_blocking_and_background_frames() -> None:
    frames = _axes_frames(3)
    # A lower-priority heartbeat can block the lowest PDO once (non-preemptive):
    hb = CanFrame(0x701, 1, "hb", period_us=100_000.0)
    resp = can_response_times_us([*frames, hb], CanParams(), 1000.0)
    assert resp[3] == pytest.approx(865.0 + can_frame_bits(1))  # RPDO3, 0x203
    # A higher-priority EMCY budget (one 8-byte frame per 2 ms) interferes once.
    emcy = CanFrame(0x081, 8, "emcy", period_us=2000.0)
    resp = can_response_times_us([*frames, emcy], CanParams(), 1000.0)
    assert resp[3] == pytest.approx(865.0 + 135.0)
    # One per 500 µs: 86.5 % + 27 % > 100 %: no bound.
    emcy = CanFrame(0x081, 8, "emcy", period_us=500.0)
    assert can_response_times_us([*frames, emcy], CanParams(), 1000.0)[3] is None


def test_davis_2007_counts_a_later_instance_in_the_busy_period() -> None:
    # Davis et al. 2007's point: the worst response may be a later instance in
    # the busy period. Frames of 135 µs, periods 300 / 400 / 650 µs, all queued at 0:
    # A 0-135, B 135-270, C#1 270-405 (R = 405), A 405-540, B 540-675, A 675-810,
    # B 810-945, A 945-1080, C#2 (queued at 650) 1080-1215: R = 565.
    a = CanFrame(0x001, 8, "a", period_us=300.0)
    b = CanFrame(0x002, 8, "b", period_us=400.0)
    c = CanFrame(0x003, 8, "c", period_us=650.0)
    assert can_response_times_us([a, b, c], CanParams(1_000_000), 1e6) == pytest.approx((270.0, 405.0, 565.0))


def test_heartbeat_budget_adds_load_and_lowers_max_rate() -> None:
    hb = [CanFrame(0x700 + i, 1, period_us=1000.0) for i in range(1, 4)]
    r = can_cycle(_axes_frames(3) + hb, CanParams(), 1000.0)
    share = 3 * can_frame_bits(1) / 1000.0
    assert r.load_percent == pytest.approx((0.865 + share) * 100)
    assert r.max_rate_hz == pytest.approx((1 - share) * 1e6 / 865.0)


# --------------------------------------------------------------------- CAN FD


def test_fd_dlc_rounding() -> None:
    assert [can_fd_length(n) for n in (8, 9, 13, 17, 21, 25, 33, 49, 64)] == [
        8, 12, 16, 20, 24, 32, 48, 64, 64,
    ]  # fmt: skip
    with pytest.raises(ValueError):
        can_fd_length(65)


def test_fd_64_byte_frame_lengths_linux_length_h() -> None:
    # can_facts.md / Linux include/linux/can/length.h: 579 bits without
    # dynamic stuffing, 712 worst case (standard ID, IFS included).
    assert can_frame_bits(64, fd=True, worst_case=False) == 579
    assert can_frame_bits(64, fd=True) == 712


def test_fd_crc17_and_crc21_and_fixed_stuff_bits() -> None:
    # 16 bytes: CRC-17 -> stuff count 4 + 17 = 21 bits + 6 fixed stuff bits.
    assert can_frame_bits(16, fd=True, worst_case=False) == 22 + 128 + 21 + 6 + 13
    # 20 bytes: CRC-21 -> 25 bits + 7 fixed stuff bits.
    assert can_frame_bits(20, fd=True, worst_case=False) == 22 + 160 + 25 + 7 + 13
    # 10 bytes are sent as 12.
    assert can_frame_bits(10, fd=True) == can_frame_bits(12, fd=True)
    # Extended ID adds SRR + 18 ID bits = 19 header bits.
    assert can_frame_bits(64, fd=True, extended=True, worst_case=False) == 579 + 19


def test_fd_brs_64_bytes_at_1_and_5_mbit() -> None:
    # can_facts.md: about 140 µs at 1/5 Mbit/s without dynamic stuffing.
    t = can_frame_time_us(64, bitrate=1_000_000, data_bitrate=5_000_000, fd=True, worst_case=False)
    assert t == pytest.approx(30 + 549 / 5)  # 30 nominal bits, 549 at 5 Mbit/s
    assert t == pytest.approx(140, rel=0.01)
    # Without BRS everything is at the nominal rate.
    assert can_frame_time_us(64, bitrate=1_000_000, fd=True, worst_case=False) == pytest.approx(579)


# ------------------------------------------------------------------- EtherCAT


def test_minimum_frame_is_padded_to_64_bytes_plus_preamble_and_ifg() -> None:
    assert ethernet_wire_bytes([1]) == 8 + 64 + 12
    assert ethernet_wire_bytes([32]) == 8 + 64 + 12  # 2 + 12 + 32 = 46: exactly the minimum
    assert ethernet_wire_bytes([33]) == 8 + 14 + 47 + 4 + 12


def test_full_frame_matches_published_122_us() -> None:
    # ETHERNET Powerlink "Performance": one maximum-length Ethernet frame is
    # back at the sender after 122 µs. Ours: 1486 bytes of datagram data =
    # 1500-byte payload, 1526 bytes incl. preamble = 122.08 µs; +IFG 123.04 µs.
    frames = ethercat_frames([EcatSlave(1486, 0)], EthercatParams())
    assert len(frames) == 1 and frames[0].wire_bytes == 1538
    assert wire_time_us(8 * (1538 - 12), 100e6) == pytest.approx(122.08)
    r = ethercat_cycle([EcatSlave(1486, 0)], EthercatParams(cable_m=0, forwarding_delay_us=0), 1000)
    assert r.wire_time_us == pytest.approx(122, rel=0.10)


def test_frames_split_at_1486_bytes_and_dc_datagram() -> None:
    f = ethercat_frames([EcatSlave(1000, 487)], EthercatParams())
    assert [g for fr in f for g in fr.datagrams] == [("LRW", 1486), ("LRW", 1)]
    f = ethercat_frames([EcatSlave(800, 0)], EthercatParams(dc=True))
    assert f[0].datagrams == (("FRMW", 8), ("LRW", 800))
    assert f[0].wire_bytes == 8 + 14 + 2 + 12 + 8 + 12 + 800 + 4 + 12
    f = ethercat_frames([EcatSlave(1480, 0)], EthercatParams(dc=True))
    assert [g for fr in f for g in fr.datagrams] == [("FRMW", 8), ("LRW", 1466), ("LRW", 14)]


def test_lrw_overlap_and_lrd_lwr() -> None:
    slaves = [EcatSlave(16, 20)] * 30
    plain = ethercat_frames(slaves, EthercatParams())
    assert plain[0].datagrams == (("LRW", 1080),)
    over = ethercat_frames(slaves, EthercatParams(overlap=True))
    assert over[0].datagrams == (("LRW", 600),)
    sep = ethercat_frames(slaves, EthercatParams(mode="lrd_lwr"))
    assert sep[0].datagrams == (("LWR", 480), ("LRD", 600))
    assert sep[0].wire_bytes == plain[0].wire_bytes + 12  # one more datagram header + WKC


def test_round_trip_adds_forwarding_and_cable() -> None:
    slaves = [EcatSlave(8, 8)] * 10
    r = ethercat_cycle(slaves, EthercatParams(cable_m=2.0), 1000)
    assert r.extra("forwarding_us") == pytest.approx(10 * 1.0)
    assert r.extra("propagation_us") == pytest.approx(2 * 10 * 2.0 * 0.005)
    assert r.extra("round_trip_us") == pytest.approx(r.wire_time_us + 10 + 0.2)
    assert r.max_rate_hz == pytest.approx(1e6 / (r.wire_time_us + 10.2))


# Beckhoff/ETG performance figures (docs/bandwidth.md, "EtherCAT figures").
# Beckhoff publishes the 100BASE-TX port delay (EK1101: 1 µs typ.) but no
# per-terminal EBUS delay; we take it from ONE figure and predict the others.
ETG_1000_IO_US = 30.0  # Beckhoff: 1000 distributed digital I/O in 30 µs
ETG_12000_IO_US = 300.0  # Beckhoff: 1486 bytes (~12,000 digital I/O) in 300 µs
ETG_100_AXES_US = 100.0  # Beckhoff/ETG: 100 servo axes (8 bytes in + out) every 100 µs


def _terminals(io_bits: int, per_terminal: int = 8) -> list[EcatSlave]:
    """Digital terminals of 8 channels: half inputs, half outputs, 1 byte each."""
    n = io_bits // per_terminal
    return [EcatSlave(1, 0) if i % 2 else EcatSlave(0, 1) for i in range(n)]


def _ebus_delay_from_1000_io() -> float:
    slaves = _terminals(1000)  # 125 terminals, 125 bytes: "a transfer of 125 byte"
    r = ethercat_cycle(slaves, EthercatParams(forwarding_delay_us=0.0, cable_m=0.0), 1000)
    return (ETG_1000_IO_US - r.wire_time_us - 1.0) / len(slaves)  # minus the EK1100 coupler


def test_etg_1000_io_implies_a_sub_microsecond_ebus_delay() -> None:
    d = _ebus_delay_from_1000_io()
    assert 0.05 < d < 1.0  # far below the 1 µs of a 100BASE-TX port pair: plausible for EBUS


def test_etg_12000_io_predicted_within_10_percent() -> None:
    d = _ebus_delay_from_1000_io()
    slaves = _terminals(11_888)  # 1486 bytes
    r = ethercat_cycle(slaves, EthercatParams(forwarding_delay_us=d, cable_m=0.0), 1000)
    assert r.frames_per_cycle == 1
    rtt = r.extra("round_trip_us")
    assert isinstance(rtt, float)
    assert rtt + 1.0 == pytest.approx(ETG_12000_IO_US, rel=0.10)


def test_etg_100_servo_axes() -> None:
    # 100 axes x (8 bytes out + 8 in), overlapping LRW + DC datagram, EBUS-class delay:
    d = _ebus_delay_from_1000_io()
    axes = [EcatSlave(8, 8)] * 100
    r = ethercat_cycle(axes, EthercatParams(overlap=True, dc=True, forwarding_delay_us=d), 10_000)
    rtt = r.extra("round_trip_us")
    assert isinstance(rtt, float)
    assert rtt <= ETG_100_AXES_US and r.extra("fits_cycle") is True
    assert rtt == pytest.approx(ETG_100_AXES_US, rel=0.25)
    # Without overlap the 1600 bytes need two frames and do not fit in 100 µs.
    r2 = ethercat_cycle(axes, EthercatParams(dc=True, forwarding_delay_us=d), 10_000)
    assert r2.frames_per_cycle == 2 and r2.extra("fits_cycle") is False


# ------------------------------------------------------- the seed's exercises

SEED_FRAME_BITS = 130  # 62.4.1: "11-bit ID + 8 bytes + overhead ≈ 130 bits"


def test_seed_62_4_1_with_the_seeds_130_bits() -> None:
    # (a) one frame at 1 Mbit/s
    one = can_cycle([CanFrame(0x001, 8, frame_bits=SEED_FRAME_BITS)], CanParams(), 1000.0)
    assert one.wire_time_us == pytest.approx(130.0)
    # (b) 12 motors, command + feedback = 24 frames (no SYNC in the seed's count)
    frames = [CanFrame(i, 8, frame_bits=SEED_FRAME_BITS) for i in range(1, 25)]
    r = can_cycle(frames, CanParams(), 1000.0)
    assert r.wire_time_us == pytest.approx(3120.0)
    assert r.load_percent > 100  # the seed's answer: 1 kHz does not fit on one bus
    assert r.max_rate_hz == pytest.approx(1e6 / 3120)
    # The seed's own layout: 3 motors per bus, 6 x 130 = 780 bits = 0.78 ms.
    r3 = can_cycle(frames[:6], CanParams(), 1000.0)
    assert r3.wire_time_us == pytest.approx(780.0) and r3.load_percent == pytest.approx(78.0)


def test_seed_62_4_1_with_our_worst_case_model() -> None:
    frames = [CanFrame(0x100 + i, 8) for i in range(24)]
    r = can_cycle(frames, CanParams(), 1000.0)
    assert r.wire_time_us == pytest.approx(24 * 135.0)  # 3240 µs: 3.8 % above the seed's 3120
    assert r.extra("nominal_wire_time_us") == pytest.approx(24 * 111.0)


SEED_ETH_OVERHEAD = 42  # 62.5.1: preamble + header + CRC + IFG


def test_seed_62_5_1_with_the_seeds_assumptions() -> None:
    payload = 30 * (16 + 20)  # RxPDO 16 + TxPDO 20 bytes per motor, one frame
    seed_us = wire_time_us(8 * (payload + SEED_ETH_OVERHEAD), 100e6)
    assert seed_us == pytest.approx(89.76)
    # Our layout adds the EtherCAT header (2) and datagram header + WKC (12): 52 bytes.
    r = ethercat_cycle([EcatSlave(16, 20)] * 30, EthercatParams(), 1000)
    assert r.frames_per_cycle == 1
    assert r.wire_time_us == pytest.approx(wire_time_us(8 * (payload + 52), 100e6))
    assert r.wire_time_us == pytest.approx(seed_us, rel=0.01)
    # Compared with CAN: ~35x less bus time than 60 classic frames at 1 Mbit/s.
    can = can_cycle([CanFrame(i, 8, frame_bits=SEED_FRAME_BITS) for i in range(60)], CanParams(), 1000)
    assert can.wire_time_us / r.wire_time_us > 30


# ------------------------------------------------------ adapters and network

EPOS4 = Path(__file__).resolve().parents[1] / "data" / "ethercat_driver_ros2" / "maxon_epos4_50_5.yaml"

CAN_MAP = """
name: can_drive
vendor_id: 1
product_id: 2
canopen: {heartbeat_ms: 100}
rpdo:
  - index: 0x1600
    channels:
      - {index: 0x6040, sub_index: 0, type: uint16}
      - {index: 0x607A, sub_index: 0, type: int32}
      - {index: 0x60B1, sub_index: 0, type: int16}
tpdo:
  - index: 0x1A00
    channels:
      - {index: 0x6041, sub_index: 0, type: uint16}
      - {index: 0x6064, sub_index: 0, type: int32}
      - {index: 0x6077, sub_index: 0, type: int16}
"""


@dataclass(frozen=True)
class FakeSlave:
    name: str
    map: DriveMap
    node_id: int | None = None


@dataclass(frozen=True)
class FakeBus:
    name: str
    type: str
    slaves: tuple[FakeSlave, ...]
    cycle_time_us: float = 1000.0
    bitrate: int | None = None
    data_bitrate: int | None = None


@dataclass(frozen=True)
class FakeNetwork:
    buses: tuple[FakeBus, ...]
    cycle_time_us: float = 1000.0


def _can_map() -> DriveMap:
    return drive_map_from_text(CAN_MAP)


def test_canopen_bus_from_maps() -> None:
    m = _can_map()
    bus = FakeBus("arm", "canopen", tuple(FakeSlave(f"j{i}", m, i) for i in (1, 2, 3)), bitrate=1_000_000)
    r = bus_bandwidth(bus)
    assert r.frames_per_cycle == 7 and r.bytes_per_cycle == 48
    assert r.wire_bits_per_cycle == 865
    hb_share = 3 * can_frame_bits(1) / 100_000  # three heartbeats every 100 ms
    assert r.load_percent == pytest.approx((0.865 + hb_share) * 100)
    # Lowest-priority PDO: RPDO1 of node 3 (0x203), blocked by a heartbeat (0x70x).
    assert r.extra("worst_response_frame") == "j3 RPDO1"
    assert r.extra("worst_response_us") == pytest.approx(865 + can_frame_bits(1))
    off = bus_bandwidth(bus, can=CanOptions(heartbeat=False, sync=False))
    assert off.frames_per_cycle == 6 and off.load_percent == pytest.approx(81.0)


def test_can_bus_needs_node_id_and_small_pdos() -> None:
    bus = FakeBus("arm", "canopen", (FakeSlave("j", _can_map(), None),))
    with pytest.raises(PdoMapError, match="node_id"):
        bus_bandwidth(bus)
    big = FakeBus("x", "canopen", (FakeSlave("epos", drive_map_from_text(EPOS4.read_text()), 1),))
    with pytest.raises(PdoMapError, match="classic CAN carries at most 8"):
        bus_bandwidth(big)


def test_can_fd_bus_from_maps() -> None:
    epos = drive_map_from_text(EPOS4.read_text())  # 25-byte RxPDO: needs CAN FD
    bus = FakeBus("fd", "canopen", (FakeSlave("e", epos, 1),), bitrate=1_000_000, data_bitrate=5_000_000)
    r = bus_bandwidth(bus, can=CanOptions(heartbeat=False))
    assert r.frames_per_cycle == 3
    assert r.extra("data_bitrate") == 5_000_000
    assert r.wire_time_us < r.wire_bits_per_cycle  # data phase at 5 Mbit/s


def test_ethercat_bus_from_maps() -> None:
    epos = drive_map_from_text(EPOS4.read_text())
    bus = FakeBus("legs", "ethercat", tuple(FakeSlave(f"a{i}", epos) for i in range(12)))
    r = bus_bandwidth(bus)
    out_b = (sum(p.bits for p in epos.rpdo) + 7) // 8
    in_b = (sum(p.bits for p in epos.tpdo) + 7) // 8
    assert r.bytes_per_cycle == 12 * (out_b + in_b)
    assert r.extra("dc") is True  # the EPOS4 map sets assign_activate
    assert r.wire_time_us == pytest.approx(wire_time_us(8 * (12 * (out_b + in_b) + 52 + 20), 100e6))


def test_network_names_the_bottleneck() -> None:
    m = _can_map()
    epos = drive_map_from_text(EPOS4.read_text())
    net = FakeNetwork(
        (
            FakeBus("legs", "ethercat", tuple(FakeSlave(f"a{i}", epos) for i in range(12))),
            FakeBus("arm", "canopen", tuple(FakeSlave(f"j{i}", m, i) for i in (1, 2)), bitrate=1_000_000),
            FakeBus(
                "hand", "canopen", tuple(FakeSlave(f"f{i}", m, i) for i in range(1, 7)), bitrate=1_000_000
            ),
            FakeBus("sim", "sim", (FakeSlave("s", m),)),
        )
    )
    res = network_bandwidth(net)
    assert res.bottleneck == "hand"
    j = res.to_json()
    assert j["bottleneck"] == "hand" and j["rate_hz"] == 1000
    buses = j["buses"]
    assert isinstance(buses, list) and [b["name"] for b in buses] == ["legs", "arm", "hand", "sim"]
    for b in buses:
        assert {"name", "type", "frames_per_cycle", "bytes_per_cycle", "wire_time_us",
                "load_percent", "max_rate_hz"} <= set(b)  # fmt: skip
    json.dumps(j)  # JSON-serialisable
    # Faster hand bus: the bottleneck moves.
    fast = FakeBus("hand", "canopen", net.buses[2].slaves, bitrate=1_000_000, data_bitrate=8_000_000)
    net2 = FakeNetwork(
        (net.buses[0], net.buses[1], FakeBus("hand", "rawcan", fast.slaves[:1], bitrate=1_000_000))
    )
    assert network_bandwidth(net2).bottleneck == "arm"


# ---------------------------------------------------------------------- CLI


def _write_network(tmp_path: Path) -> Path:
    (tmp_path / "can.yaml").write_text(CAN_MAP)
    (tmp_path / "epos.yaml").write_text(EPOS4.read_text())
    net = tmp_path / "net.yaml"
    net.write_text(
        "cycle_time_us: 1000\n"
        "buses:\n"
        "  - name: legs\n    type: ethercat\n    interface: eth0\n    slaves:\n"
        "      - {name: 'leg{i}', map: epos.yaml, count: 12}\n"
        "  - name: arm\n    type: canopen\n    interface: can0\n    can_interface: virtual\n"
        "    bitrate: 1000000\n    slaves:\n"
        "      - {name: j1, map: can.yaml, node_id: 1}\n"
        "      - {name: j2, map: can.yaml, node_id: 2}\n"
        "      - {name: j3, map: can.yaml, node_id: 3}\n"
        "      - {name: j4, map: can.yaml, node_id: 4}\n"
    )
    return net


def test_cli_json(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    net = _write_network(tmp_path)
    assert main(["bandwidth", str(net), "--json"]) == 3  # the CAN arm needs 114 % of its bus at 1 kHz
    out = json.loads(capsys.readouterr().out)
    assert out["rate_hz"] == 1000 and out["bottleneck"] == "arm" and out["overloaded"] == ["arm"]
    arm = next(b for b in out["buses"] if b["name"] == "arm")
    assert arm["frames_per_cycle"] == 9 and arm["wire_bits_per_cycle"] == 4 * 2 * 135 + 55
    assert main(["bandwidth", str(net), "--json", "--rate", "2000"]) == 3
    out2 = json.loads(capsys.readouterr().out)
    assert out2["rate_hz"] == 2000
    arm2 = next(b for b in out2["buses"] if b["name"] == "arm")
    assert arm2["load_percent"] > 2 * 0.99 * arm["load_percent"] - 1


def test_cli_table_and_plot(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    net = _write_network(tmp_path)
    png = tmp_path / "cycle.png"
    assert main(["bandwidth", str(net), "--plot", str(png)]) == 3  # drawn and printed all the same
    text = capsys.readouterr().out
    assert "legs" in text and "arm" in text and "bottleneck: arm" in text
    assert png.stat().st_size > 1000


def test_cli_plot_without_matplotlib(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    import sys

    net = _write_network(tmp_path)
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    assert main(["bandwidth", str(net), "--plot", str(tmp_path / "x.png")]) == 1
    assert "pip install 'fieldbus[plot]'" in capsys.readouterr().err


def test_cli_rejects_bad_rate(tmp_path: Path) -> None:
    net = _write_network(tmp_path)
    with pytest.raises(SystemExit):
        main(["bandwidth", str(net), "--rate", "0"])


def test_infinite_values_stay_out_of_json() -> None:
    r = can_cycle(_axes_frames(12), CanParams(), 1000.0)
    text = json.dumps(r.to_json(), allow_nan=False)
    assert "worst_response_us" in text
    assert not math.isnan(r.load_percent)
