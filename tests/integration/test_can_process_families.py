"""``python -m sim_slaves.can_process``: every raw-CAN family, per-bus kinds, maps and nodes in one process."""

from __future__ import annotations

import pytest

pytest.importorskip("can")

import fieldbus
from sim_slaves.can_process import bus_specs, main, parse_args

ODRIVE = str(fieldbus.PDO_MAPS / "odrive_s1.yaml")
SERVO = str(fieldbus.PDO_MAPS / "cubemars_ak80_9_servo.yaml")


def test_kind_map_and_nodes_after_a_channel_are_that_bus_s() -> None:
    common = ["--kind", "auto", "--map", ODRIVE, "--nodes", "1,2", "--interface", "fieldbus_udp"]
    first = ["--channel", "239.1.1.1", "--option", "port=4000"]
    second = ["--channel", "239.1.1.2", "--kind", "cubemars", "--map", SERVO, "--nodes", "5"]
    args = parse_args([*common, *first, *second])
    assert bus_specs(args) == [("auto", ODRIVE, [1, 2]), ("cubemars", SERVO, [5])]


def test_a_bus_without_a_map_is_refused_by_name(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        parse_args(["--kind", "auto", "--nodes", "1", "--channel", "239.1.1.1"])
    assert "bus 239.1.1.1: no --map" in capsys.readouterr().err


def test_a_map_of_another_family_than_kind_is_refused_before_ready(
    capsys: pytest.CaptureFixture[str],
) -> None:
    argv = ["--kind", "damiao", "--map", ODRIVE, "--nodes", "1", "--interface", "virtual"]
    assert main([*argv, "--channel", "can-process-families-test"]) == 2
    out = capsys.readouterr()
    assert "ready" not in out.out
    assert "--kind damiao: the map odrive_s1 is of family odrive" in out.err
