"""CAN emulators in their own processes, over python-can's udp_multicast interface.

The master (the real CANopen and raw-CAN backends) runs here; the emulated nodes
run in child processes (``sim_slaves.can_process``), so the two no longer share
one interpreter lock. The seed's layout: 4 CAN buses with 3 MIT-mode motors each.

The emulators answer on the wall clock in their own processes: on a loaded
machine a reply may come later than the receive timeout (a counted miss). The
tests are about the layout across processes, not its timing: they run until
what they assert has happened, with bounds in cycles for a loaded machine.
"""

from __future__ import annotations

import json
import time
from contextlib import ExitStack
from pathlib import Path

import pytest

pytest.importorskip("can")
pytest.importorskip(
    "msgpack", reason="python-can's udp_multicast interface needs msgpack (pip install msgpack)"
)

from fieldbus import PDO_MAPS
from fieldbus.cli import main
from fieldbus.commands.demo import DEMO_MAP
from fieldbus.core.cia402 import Cia402Controller, Goal, Mode, State402, decode_state
from fieldbus.errors import PdoMapError
from fieldbus.network import open_network
from sim_slaves.can_process import can_emulator_process, udp_bus

pytestmark = pytest.mark.timeout(180)
MIT_MAP = Path(PDO_MAPS) / "cubemars_ak80_9_mit.yaml"


def _seed_network(tmp_path: Path, buses: list, timeout_us: int = 2000) -> Path:  # type: ignore[type-arg]
    f = tmp_path / "legs.yaml"
    f.write_text(
        f"cycle_time_us: 1000\nreceive_timeout_us: {timeout_us}\nsafe_stop_after: 100000\nbuses:\n"
        + "".join(
            f"  - {{name: leg{i}, type: rawcan, {b.network_keys()},\n"
            f"     slaves: [{{name: 'leg{i}_m{{i}}', map: '{MIT_MAP}', node_id: 1, count: 3}}]}}\n"
            for i, b in enumerate(buses)
        )
    )
    return f


def test_four_buses_of_three_mit_motors_each_in_their_own_processes(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    buses = [udp_bus(i) for i in range(4)]
    # 20 ms: python-can's udp_multicast (msgpack per frame) with 4 emulator processes on 2 CPUs answers a
    # back-to-back exchange in 1.5-3.7 ms on a quiet machine; a reply later than the timeout is a counted
    # miss (never taken for the next cycle's)
    net_file = _seed_network(tmp_path, buses, timeout_us=20_000)
    with ExitStack() as stack:
        for b in buses:
            stack.enter_context(can_emulator_process("mit", MIT_MAP, [1, 2, 3], b, dt_s=0.001))
        with open_network(net_file) as net:
            op = net.bring_up()
            fresh = [0] * 4
            for _ in range(3000):  # until every bus had 200 cycles with a reply from each of its motors
                res = op.exchange()
                for i, st in enumerate(res.buses):
                    fresh[i] += st.verdict.name == "OK"
                if min(fresh) >= 200:
                    break
            for i in range(4):
                group = op[f"leg{i}"]
                # every motor answers with its own position, the emulator in its process keeps it near 0
                assert group.inputs["position"].shape == (3,)
    assert min(fresh) >= 200, fresh  # on a quiet machine: within about 210 cycles
    # the seed's bus load: 4 buses at 1 kHz, 3 motors each (command + reply per motor and cycle)
    assert main(["bandwidth", str(net_file), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert [b["frames_per_cycle"] for b in report["buses"]] == [6, 6, 6, 6]
    assert all(60 < b["load_percent"] < 90 and b["schedulable"] for b in report["buses"])


def test_canopen_nodes_in_another_process_are_configured_and_enabled(tmp_path: Path) -> None:
    where = udp_bus(5)
    f = tmp_path / "arm.yaml"
    f.write_text(
        "cycle_time_us: 5000\nreceive_timeout_us: 20000\nsafe_stop_after: 1000\nbuses:\n"
        f"  - {{name: arm, type: canopen, {where.network_keys()},\n"
        f"     slaves: [{{name: 'a{{i}}', map: '{DEMO_MAP}', node_id: 1, count: 3}}]}}\n"
    )
    with can_emulator_process("canopen", DEMO_MAP, [1, 2, 3], where, dt_s=0.005), open_network(f) as net:
        op = net.bring_up()  # identity and the SDO plan with read-back, across processes
        img = op["arm"]
        ctrl = Cia402Controller(3, mode=Mode.CSP)
        ctrl.set_goal(Goal.ENABLE)
        fresh = 0
        for _ in range(5000):  # until enabled and 200 cycles in (on a quiet machine: 300 cycles, 270 fresh)
            fresh += op.exchange().fresh
            ctrl.step(img.inputs["statusword"], img.outputs["controlword"])
            if ctrl.all_reached and fresh >= 200:
                break
        assert fresh >= 200
        assert ctrl.all_reached  # the goal, read from the statuswords the nodes sent
        assert [decode_state(int(w)) for w in img.inputs["statusword"]] == [State402.OPERATION_ENABLED] * 3


def test_one_process_serves_canopen_nodes_on_two_buses(tmp_path: Path) -> None:
    """``serve_together``: both buses' SDO plans, NMT, SYNC and heartbeats (timers) from one thread."""
    where = [udp_bus(6 + i, interface="fieldbus_udp") for i in range(2)]
    f = tmp_path / "arms.yaml"
    f.write_text(
        "cycle_time_us: 5000\nreceive_timeout_us: 20000\nsafe_stop_after: 1000\nbuses:\n"
        + "".join(
            f"  - {{name: arm{k}, type: canopen, {w.network_keys()},\n"
            f"     slaves: [{{name: 'a{k}_{{i}}', map: '{DEMO_MAP}', node_id: 1, count: 2}}]}}\n"
            for k, w in enumerate(where)
        )
    )
    with can_emulator_process("canopen", DEMO_MAP, [1, 2], where, dt_s=0.005) as proc:
        import can

        # a listener on the second bus: heartbeats keep coming while the master is silent there
        with can.Bus(interface="fieldbus_udp", channel=where[1].channel, **dict(where[1].options)) as spy:
            heartbeats = set()
            deadline = time.monotonic() + 3.0
            while len(heartbeats) < 2 and time.monotonic() < deadline:
                msg = spy.recv(timeout=0.5)
                if msg is not None and 0x701 <= msg.arbitration_id <= 0x702:
                    heartbeats.add(msg.arbitration_id)
        assert heartbeats == {0x701, 0x702}
        with open_network(f) as net:
            op = net.bring_up()
            ctrls = {name: Cia402Controller(2, mode=Mode.CSP) for name in ("arm0", "arm1")}
            for c in ctrls.values():
                c.set_goal(Goal.ENABLE)
            for _ in range(5000):  # until both arms are enabled (on a quiet machine within 300 cycles)
                op.exchange()
                for name, c in ctrls.items():
                    c.step(op[name].inputs["statusword"], op[name].outputs["controlword"])
                if all(c.all_reached for c in ctrls.values()):
                    break
            for name in ctrls:
                words = op[name].inputs["statusword"]
                assert [decode_state(int(w)) for w in words] == [State402.OPERATION_ENABLED] * 2, name
        assert proc.poll() is None  # one process, still serving


def test_the_command_line_gives_each_channel_its_options() -> None:
    from sim_slaves.can_process import bus_arguments, parse_args

    args = parse_args(
        [
            "--kind",
            "mit",
            "--map",
            "m.yaml",
            "--nodes",
            "1",
            "--interface",
            "fieldbus_udp",
            "--option",
            "bitrate=1000000",
            "--channel",
            "239.1.1.1",
            "--option",
            "port=4000",
            "--channel",
            "239.1.1.2",
            "--option",
            "port=4001",
            "--option",
            "fd=false",
        ]
    )
    assert bus_arguments(args) == [
        {"interface": "fieldbus_udp", "channel": "239.1.1.1", "bitrate": 1000000, "port": 4000},
        {"interface": "fieldbus_udp", "channel": "239.1.1.2", "bitrate": 1000000, "port": 4001, "fd": False},
    ]
    with pytest.raises(SystemExit):
        parse_args(["--kind", "mit", "--map", "m.yaml", "--nodes", "1"])  # no --channel


def test_can_options_are_checked_where_they_are_written(tmp_path: Path) -> None:
    f = tmp_path / "bad.yaml"
    f.write_text(
        "buses:\n  - {name: a, type: rawcan, interface: x, can_interface: udp_multicast,\n"
        f"     can_options: {{channel: y}}, slaves: [{{name: m, map: '{MIT_MAP}', node_id: 1}}]}}\n"
    )
    with pytest.raises(PdoMapError, match="set by the bus itself") as info:
        open_network(f)
    assert info.value.line == 3 and info.value.path == "buses[0].can_options.channel"
    f.write_text(
        "buses:\n  - {name: a, type: ethercat, interface: eth0, can_options: {port: 1},\n"
        f"     slaves: [{{name: m, map: '{MIT_MAP}'}}]}}\n"
    )
    with pytest.raises(PdoMapError, match="for CAN buses"):
        open_network(f)
