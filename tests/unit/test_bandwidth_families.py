"""Bandwidth of the raw-CAN actuator families (Damiao, ODrive, CubeMars MIT) from their shipped maps.

Expected figures are hand-computed bit counts of classic CAN frames with worst-case stuffing
(Davis et al. 2007, eq. 1: 8 data bytes 135 bits, 6 bytes 115, a remote frame / 0 bytes 55, standard
ids, 3-bit interframe space included), at 1 Mbit/s one bit = 1 us; frame ids from the vendors' protocol
descriptions (Damiao: id + mode offset, replies on MST_ID = id + 0x10; ODrive CANSimple: node << 5 | cmd).
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import pytest

from fieldbus import PDO_MAPS
from fieldbus.cli import main
from fieldbus.core.bandwidth import family_frames, network_bandwidth, protocol_frames
from fieldbus.core.network import load_network
from fieldbus.core.pdo import load_drive_map

B8, B6, RTR = 135, 115, 55  # worst-case bits: 8-byte, 6-byte data frame, remote frame


def _layout(tmp_path: Path, map_name: str, per_bus: list[int], rate_hz: float = 1000.0) -> Path:
    """A network of len(per_bus) classic CAN buses at 1 Mbit/s, per_bus[k] motors of ``map_name`` on bus k."""
    lines = [f"cycle_time_us: {1e6 / rate_hz:g}", "buses:"]
    for k, n in enumerate(per_bus):
        lines.append(
            f"  - {{name: can{k}, type: rawcan, interface: can{k}, bitrate: 1000000, slaves: "
            f"[{{name: 'm{k}_{{i}}', map: {Path(PDO_MAPS) / map_name}, node_id: 1, count: {n}}}]}}"
        )
    path = tmp_path / "net.yaml"
    path.write_text("\n".join(lines) + "\n")
    return path


def test_damiao_4_buses_of_3_at_1_khz_frames_per_mode(tmp_path: Path) -> None:
    result = network_bandwidth(load_network(_layout(tmp_path, "damiao_dm_j4310.yaml", [3, 3, 3, 3])))
    for k, bus in enumerate(result.buses):
        assert bus.frames_per_cycle == 6 and bus.wire_bits_per_cycle == 3 * (B8 + B8)
        assert bus.load_percent == pytest.approx(81.0)
        assert [s.label for s in bus.timeline] == [f"m{k}_{i} mit command" for i in range(3)] + [
            f"m{k}_{i} reply" for i in range(3)
        ]
    # the map's mode sets the command's CAN id: MIT at id, velocity at 0x200 + id; replies on id + 0x10
    cfg = load_drive_map(Path(PDO_MAPS) / "damiao_dm_j4310.yaml").rawcan
    assert cfg is not None
    for mode, offset in (
        ("mit", 0),
        ("position_velocity", 0x100),
        ("velocity", 0x200),
        ("position_force", 0x300),
    ):
        command, reply = family_frames("j", cfg, 2, mode=mode)
        assert (command.can_id, command.data_bytes, command.label) == (offset + 2, 8, f"j {mode} command")
        assert (reply.can_id, reply.data_bytes, reply.after) == (0x12, 8, command.label)


@pytest.mark.parametrize("map_name", ["odrive_s1.yaml", "odrive_3_6.yaml"])
def test_odrive_set_point_rtr_estimates_and_heartbeat(tmp_path: Path, map_name: str) -> None:
    result = network_bandwidth(load_network(_layout(tmp_path, map_name, [3, 3, 3, 3])))
    per_motor = B8 + RTR + B8  # Set_Input_Pos, Get_Encoder_Estimates RTR, its answer
    heartbeat_share = 3 * B8 / 100_000  # 8 bytes every 100 ms per motor, 1 us per bit
    for bus in result.buses:
        assert bus.frames_per_cycle == 9 and bus.wire_bits_per_cycle == 3 * per_motor
        assert bus.wire_time_us == pytest.approx(975.0)
        assert bus.load_percent == pytest.approx(97.5 + 100 * heartbeat_share)
        assert bus.max_rate_hz == pytest.approx((1 - heartbeat_share) * 1e6 / 975.0)
        assert bus.extra("background_load_percent") == pytest.approx(100 * heartbeat_share)
    cfg = load_drive_map(Path(PDO_MAPS) / map_name).rawcan
    assert cfg is not None
    assert cfg.odrive is not None
    velocity = replace(cfg, odrive=replace(cfg.odrive, mode="velocity"))
    # as the family reports them on a CAN FD bus: the remote frame stays classic (CAN FD has none)
    frames = [f for f, _ in protocol_frames("a", replace(velocity, protocol=velocity), 3, None, fd=True)]
    ids = [(f.can_id, f.data_bytes, f.period_us, f.fd) for f in frames]
    assert ids == [
        (3 << 5 | 0x0D, 8, None, True),  # Set_Input_Vel
        (3 << 5 | 0x09, 0, None, False),  # Get_Encoder_Estimates, remote
        (3 << 5 | 0x09, 8, None, True),  # its answer
        (3 << 5 | 0x01, 8, 100_000.0, True),  # heartbeat
    ]


def test_30_joint_humanoid_on_classic_can_per_family(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # 30 Damiao joints at 1 kHz: 8 buses (4, 4, 4, 4, 4, 4, 3, 3) overload (4 x 270 us > 1 ms),
    # 10 buses of 3 fit at 81 %.
    tight = _layout(tmp_path, "damiao_dm_j4310.yaml", [4] * 6 + [3] * 2)
    assert main(["bandwidth", str(tight), "--json"]) == 3
    out = json.loads(capsys.readouterr().out)
    assert out["overloaded"] == [f"can{k}" for k in range(6)]
    assert out["buses"][0]["load_percent"] == pytest.approx(108.0)
    roomy = _layout(tmp_path, "damiao_dm_j4310.yaml", [3] * 10)
    assert main(["bandwidth", str(roomy), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert {b["load_percent"] for b in out["buses"]} == {81.0}
    # ODrive: 4 per bus is 4 x 325 us = 1.3 ms > 1 ms; 3 per bus fit (97.9 %)
    odrive = _layout(tmp_path, "odrive_s1.yaml", [3] * 10)
    assert main(["bandwidth", str(odrive), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["buses"][0]["load_percent"] == pytest.approx(97.5 + 0.405)
    # CubeMars AK80-9 MIT: 8-byte command, 6-byte reply [id, p16, v12, i12]; 4 per bus fill 1 ms exactly
    cubemars = _layout(tmp_path, "cubemars_ak80_9_mit.yaml", [4] * 7 + [2])
    assert main(["bandwidth", str(cubemars), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert (
        out["buses"][0]["wire_bits_per_cycle"] == 4 * (B8 + B6) and out["buses"][0]["load_percent"] == 100.0
    )
