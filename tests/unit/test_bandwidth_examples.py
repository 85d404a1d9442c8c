"""The 30-axis humanoid example: why the seed recommends EtherCAT over 6 CAN buses."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from fieldbus.cli import main

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


def bandwidth(capsys: pytest.CaptureFixture[str], name: str, *extra: str, code: int = 0) -> dict:  # type: ignore[type-arg]
    """``fieldbus bandwidth --json``; ``code`` 3: a bus is over 100 % load (the figures are printed all the same)."""
    assert main(["bandwidth", str(EXAMPLES / name), "--json", *extra]) == code
    return json.loads(capsys.readouterr().out)  # type: ignore[no-any-return]


def test_30_axes_fit_one_ethercat_segment_at_1khz(capsys: pytest.CaptureFixture[str]) -> None:
    r = bandwidth(capsys, "humanoid_ethercat.yaml")
    (bus,) = r["buses"]
    assert bus["type"] == "ethercat" and bus["frames_per_cycle"] == 1
    assert bus["bytes_per_cycle"] == 30 * (10 + 10)  # hardware tutorial §62.5: 600 bytes
    assert bus["load_percent"] < 10 and bus["max_rate_hz"] > 10_000


def test_6_can_buses_of_5_cannot_run_1khz(capsys: pytest.CaptureFixture[str]) -> None:
    r = bandwidth(capsys, "humanoid_can.yaml", code=3)
    assert len(r["buses"]) == 6
    assert sorted(r["overloaded"]) == sorted(b["name"] for b in r["buses"])
    for bus in r["buses"]:
        # SYNC + 5 nodes x (2 RPDO + 2 TPDO)
        assert bus["frames_per_cycle"] == 21
        assert bus["load_percent"] > 100 and bus["max_rate_hz"] < 500
    assert r["bottleneck"] in {b["name"] for b in r["buses"]}
    # even at 400 Hz each CAN bus is close to saturation
    r400 = bandwidth(capsys, "humanoid_can.yaml", "--rate", "400")
    assert all(80 < b["load_percent"] <= 100 for b in r400["buses"])


def test_demo_network_on_ethercat_uses_a_few_percent_of_the_wire(capsys: pytest.CaptureFixture[str]) -> None:
    r = bandwidth(capsys, "demo_network.yaml")
    (bus,) = r["buses"]
    assert bus["frames_per_cycle"] == 1
    assert bus["bytes_per_cycle"] == 12 * (9 + 13)  # demo_joint: 9 output + 13 input bytes per joint
    assert bus["load_percent"] < 5 and bus["max_rate_hz"] > 10_000


def test_demo_joints_on_can_need_several_buses_and_a_lower_rate(capsys: pytest.CaptureFixture[str]) -> None:
    r = bandwidth(capsys, "demo_canopen.yaml", code=3)
    one, *legs = r["buses"]
    assert r["bottleneck"] == one["name"] == "one_bus"
    assert one["frames_per_cycle"] == 1 + 12 * 4  # SYNC + 12 x (2 RPDO + 2 TPDO)
    assert one["max_rate_hz"] < 200
    assert len(legs) == 4 and all(b["frames_per_cycle"] == 13 for b in legs)
    assert all(600 < b["max_rate_hz"] < 1000 for b in legs)  # 4 buses of 3: about 700 Hz, not 1 kHz
