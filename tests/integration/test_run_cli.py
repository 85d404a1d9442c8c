"""``fieldbus run``: a network file's cycle on the in-process emulator, and a clear refusal for CAN."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from fieldbus.cli import main

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


def test_run_demo_network_on_sim(capsys: pytest.CaptureFixture[str]) -> None:
    assert (
        main(["run", str(EXAMPLES / "demo_network.yaml"), "--backend", "sim", "--cycles", "200", "--json"])
        == 0
    )
    r = json.loads(capsys.readouterr().out)
    assert (r["cycles"], r["missed"], r["safe_stops"]) == (200, 0, 0)
    assert set(r["cycle_time_us"]) == {"mean", "p99", "max"}
    (bus,) = r["buses"]
    assert (bus["type"], bus["slaves"], bus["expected_wkc"]) == ("sim", 12, 36)


def test_sim_backend_refuses_a_can_bus(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["run", str(EXAMPLES / "humanoid_can.yaml"), "--backend", "sim", "--cycles", "5"]) == 1
    err = capsys.readouterr().err
    assert "is canopen" in err and "emulates EtherCAT" in err
