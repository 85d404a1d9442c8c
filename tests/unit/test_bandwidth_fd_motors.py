"""Raw-CAN motors on a CAN FD bus: the bandwidth calculator counts their frames as FD frames.

The expected figures are computed here by hand from the field lengths of ISO 11898-1:2015 (FD base and
extended formats, CRC-17 with its stuff count and fixed stuff bits), not with the calculator's helpers.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import pytest

from fieldbus import PDO_MAPS
from fieldbus.core.bandwidth import bus_bandwidth
from fieldbus.core.pdo import load_drive_map
from fieldbus.core.pdo.model import DriveMap

NOMINAL, DATA = 1_000_000, 5_000_000
TAIL = 1 + 1 + 1 + 7 + 3  # CRC delimiter, ACK slot, ACK delimiter, EOF, interframe space (nominal rate)
CRC_FIELD = 4 + 17  # stuff count (3-bit Gray code + parity) + CRC-17 (data <= 16 bytes)
FIXED_STUFF = 6  # one before the stuff count, then one after every 4 bits of the CRC field: ceil(21 / 4)


def fd_frame_us(data_bytes: int, *, extended: bool) -> tuple[int, float]:
    """(bit times, microseconds) of one worst-case-stuffed CAN FD frame with bit-rate switching."""
    arbitration = (
        1 + 11 + (1 + 18 if extended else 0) + 1 + 1 + 1 + 1 + 1
    )  # SOF, ID, [SRR, ID ext], RRS, IDE, FDF, res, BRS
    control = 1 + 4  # ESI, DLC (data phase)
    stuffed = arbitration + control + 8 * data_bytes  # dynamic stuffing: SOF .. end of data
    stuff_all, stuff_arb = (stuffed - 1) // 4, (arbitration - 1) // 4
    nominal = arbitration + stuff_arb + TAIL
    data_phase = control + 8 * data_bytes + (stuff_all - stuff_arb) + CRC_FIELD + FIXED_STUFF
    return nominal + data_phase, nominal / (NOMINAL / 1e6) + data_phase / (DATA / 1e6)


@dataclass(frozen=True)
class Slave:
    name: str
    map: DriveMap
    node_id: int


@dataclass(frozen=True)
class Bus:
    name: str
    type: str
    slaves: tuple[Slave, ...]
    cycle_time_us: float = 1000.0
    bitrate: int | None = NOMINAL
    data_bitrate: int | None = DATA


def test_mit_motor_frames_are_fd_on_an_fd_bus() -> None:
    # (map, command bytes, reply bytes on the wire): the AK80-9 MIT reply has no temperature / error
    for name, out_b, in_b in (
        ("cubemars_ak80_9_mit.yaml", 8, 6),
        ("cubemars_ak10_9_mit.yaml", 8, 8),  # its multi-turn position is the image's, not the wire's
        ("damiao_dm_j4310.yaml", 8, 8),
    ):
        m = load_drive_map(Path(PDO_MAPS) / name)
        bus = Bus("arm", "rawcan", tuple(Slave(f"j{i}", m, i) for i in (1, 2, 3)))
        r = bus_bandwidth(bus)
        (cmd_bits, cmd_us), (rep_bits, rep_us) = (
            fd_frame_us(out_b, extended=False),
            fd_frame_us(in_b, extended=False),
        )
        assert r.frames_per_cycle == 6, name
        assert r.wire_bits_per_cycle == 3 * (cmd_bits + rep_bits), name
        assert r.wire_time_us == pytest.approx(3 * (cmd_us + rep_us)), name
    # one 8-byte frame: 34 bits at the nominal rate, 113 in the data phase: 56.6 us (135 us on classic CAN)
    assert fd_frame_us(8, extended=False) == (147, pytest.approx(56.6))


def test_cubemars_servo_frames_are_extended_fd_frames() -> None:
    m = load_drive_map(Path(PDO_MAPS) / "cubemars_ak80_9_servo.yaml")
    bus = Bus("arm", "rawcan", tuple(Slave(f"j{i}", m, i) for i in (1, 2, 3)))
    r = bus_bandwidth(bus)
    bits, us = fd_frame_us(8, extended=True)  # position-speed packet and status frame: 8 bytes each
    assert r.frames_per_cycle == 6
    assert r.wire_bits_per_cycle == 6 * bits
    assert r.wire_time_us == pytest.approx(6 * us)
