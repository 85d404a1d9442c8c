"""``python -m sim_slaves.ethercat --network``: the slaves of one EtherCAT bus, with their emulator options."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from fieldbus.commands.demo import DEMO_MAP
from fieldbus.errors import FieldbusError
from sim_slaves.drive402 import Cia402Drive
from sim_slaves.ethercat.runner import build_chain, main, network_slaves


def _net(tmp_path: Path, buses: int = 1) -> Path:
    m = json.dumps(str(DEMO_MAP))
    text = "cycle_time_us: 500\nbuses:\n"
    for b in range(buses):
        text += (
            f"  - {{name: b{b}, type: ethercat, interface: eth{b}, slaves: ["
            f"{{name: plain{b}, map: {m}}}, "
            f"{{name: slow{b}, map: {m}, emulator: {{command_delay_us: 1500, coulomb_friction_nm: 0.02}}}}]}}\n"
        )
    path = tmp_path / "net.yaml"
    path.write_text(text)
    return path


def test_the_slaves_of_the_bus_carry_their_emulator_options(tmp_path: Path) -> None:
    maps, params = network_slaves(str(_net(tmp_path)), None)
    assert [m.name for m in maps] == ["demo_joint", "demo_joint"]
    assert params[0] is None
    assert params[1] is not None
    assert params[1]["command_delay_cycles"] == 3  # 1500 us at 500 us cycles
    assert params[1]["coulomb_friction_nm"] == 0.02
    chain = build_chain([], 1, "auto", devices=maps, drive_params=params)
    apps = [s.app for s in chain.slaves]
    assert all(isinstance(a, Cia402Drive) for a in apps)
    assert [a.params.command_delay_cycles for a in apps] == [0, 3]  # type: ignore[union-attr]


def test_a_network_with_two_ethercat_buses_needs_bus(tmp_path: Path) -> None:
    net = _net(tmp_path, buses=2)
    with pytest.raises(FieldbusError, match="more than one EtherCAT bus: name one with --bus"):
        network_slaves(str(net), None)
    with pytest.raises(FieldbusError, match=r"no EtherCAT bus 'b7'.*b0, b1"):
        network_slaves(str(net), "b7")
    maps, params = network_slaves(str(net), "b1")
    assert len(maps) == 2 and params[1] is not None


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--iface", "x"], "either --map"),
        (["--iface", "x", "--map", "a.yaml", "--network", "n.yaml"], "either --map"),
        (["--iface", "x", "--network", "n.yaml", "--count", "2"], "--count repeats --map"),
        (["--iface", "x", "--map", "a.yaml", "--bus", "b0"], "--bus needs --network"),
    ],
)
def test_bad_runner_arguments_are_refused(
    args: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exc:
        main(args)
    assert exc.value.code == 2
    assert message in capsys.readouterr().err
