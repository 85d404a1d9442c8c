"""``--monitor``: the live view shows what the cycle keeps, refreshed at most 10 times a second.

Runs the sim backend (the in-process ESC chain with CiA 402 drive models) and the
CANopen backend on python-can's virtual bus; the view is rendered by rich into a
string console.
"""

from __future__ import annotations

import io
import json
import time
from pathlib import Path

import pytest

pytest.importorskip("rich")
from rich.console import Console

from fieldbus.cli import main
from fieldbus.commands.demo import DEMO_MAP
from fieldbus.core.cia402 import Cia402Controller, Goal, Mode
from fieldbus.network import open_network
from fieldbus.operations.monitor import Monitor
from fieldbus.platform.clock import VirtualClock

pytestmark = pytest.mark.timeout(120)


def _sim_net(tmp_path: Path, axes: int = 3) -> Path:
    f = tmp_path / "net.yaml"
    f.write_text(
        "cycle_time_us: 1000\nreceive_timeout_us: 500\nsafe_stop_after: 1000\nbuses:\n"
        f"  - {{name: legs, type: ethercat, interface: sim, slaves: [{{name: 'j{{i}}', map: '{DEMO_MAP}', count: {axes}}}]}}\n"
    )
    return f


def test_view_shows_states_freshness_and_misses_as_the_cycle_sees_them(tmp_path: Path) -> None:
    # on a virtual clock (1 ms of it per cycle): a loaded machine cannot make a reply late, so the
    # misses the view shows are exactly the 3 frames dropped
    clock = VirtualClock()
    with open_network(_sim_net(tmp_path), backend="sim", clock=clock) as net:
        op = net.bring_up()
        img = op["legs"]
        ctrl = Cia402Controller(3, mode=Mode.CSP)
        ctrl.set_goal(Goal.ENABLE)
        for _ in range(300):
            op.exchange()
            clock.advance(1_000_000)
            ctrl.step(img.inputs["statusword"], img.outputs["controlword"])
        mon = Monitor(op)
        snap = mon.snapshot()
        bus = snap["buses"][0]
        assert (bus["name"], bus["verdict"], bus["wkc"], bus["expected_wkc"]) == ("legs", "OK", 9, 9)
        assert [s["cia402"] for s in bus["slaves"]] == ["operation enabled"] * 3
        assert all(s["fresh"] for s in bus["slaves"]) and bus["misses"] == 0
        net.backends[0].chain.drop_frames(3, process_data=True)  # type: ignore[attr-defined]
        for _ in range(3):
            op.exchange()
            clock.advance(1_000_000)
        snap = mon.snapshot()
        bus = snap["buses"][0]
        assert bus["misses"] == 3 and bus["consecutive_misses"] == 3 and bus["verdict"] == "TIMEOUT"
        assert [s["stale_cycles"] for s in bus["slaves"]] == [3, 3, 3]
        out = io.StringIO()
        Console(file=out, width=200, force_terminal=False).print(mon.render())
        text = out.getvalue()
        assert "legs (sim): TIMEOUT" in text and "misses 3 (in a row 3)" in text
        assert text.count("stale 3") == 3 and "operation enabled" in text


def test_refreshes_at_most_ten_times_a_second_from_its_own_thread(tmp_path: Path) -> None:
    with open_network(_sim_net(tmp_path, axes=2), backend="sim") as net:
        op = net.bring_up()
        mon = Monitor(op, console=Console(file=io.StringIO(), force_terminal=True, width=160))
        renders = 0
        render = mon.render

        def counted() -> object:
            nonlocal renders
            renders += 1
            return render()

        mon.render = counted  # type: ignore[method-assign]
        t0 = time.monotonic()
        with mon:
            while time.monotonic() - t0 < 1.0:
                op.exchange()
                time.sleep(0.001)
        seconds = time.monotonic() - t0
        assert 3 <= renders <= 10 * seconds + 3, (renders, seconds)  # rich draws once more on stop


def test_canopen_view_names_nmt_states_and_the_last_emcy(tmp_path: Path) -> None:
    can = pytest.importorskip("can")
    from fieldbus.core.pdo import load_drive_map
    from sim_slaves.canopen import CanopenSimulator

    channel = f"fb-monitor-{time.monotonic_ns()}"
    f = tmp_path / "net.yaml"
    f.write_text(
        "cycle_time_us: 5000\nreceive_timeout_us: 20000\nsafe_stop_after: 1000\nbuses:\n"
        f"  - {{name: arm, type: canopen, interface: {channel}, can_interface: virtual,\n"
        f"     slaves: [{{name: 'a{{i}}', map: {json.dumps(str(DEMO_MAP))}, node_id: 1, count: 2}}]}}\n"
    )
    drive = load_drive_map(DEMO_MAP)
    with (
        can.Bus(interface="virtual", channel=channel) as bus,
        CanopenSimulator(bus, [(drive, n) for n in (1, 2)], dt_s=0.005) as sim,
        open_network(f) as net,
    ):
        op = net.bring_up()
        sim.send_emergency(2, 0x2310)
        for _ in range(40):
            op.exchange()
        slaves = Monitor(op).snapshot()["buses"][0]["slaves"]
    assert [s["state"] for s in slaves] == ["operational", "operational"]
    assert slaves[0]["last_emcy"] is None and "over-current" in slaves[1]["last_emcy"]


def test_demo_with_monitor_runs_and_prints_the_view(capsys: pytest.CaptureFixture[str]) -> None:
    # what is checked is the view; the demo runs on the wall clock, where a loaded machine's misses may
    # latch a safe stop (exit 3: the demo's own verdict, tested in test_demo)
    assert main(["demo", "--axes", "2", "--cycles", "300", "--monitor"]) in (0, 3)
    err = capsys.readouterr().err
    assert "joints (sim)" in err and "j1" in err


def test_view_shows_each_slave_s_last_clamp_with_its_channel_asked_and_sent(tmp_path: Path) -> None:
    """Before, a clamp showed only as a bus counter (output_clamps); now per slave: which channel, why,
    the value asked and the one sent."""
    joint = tmp_path / "joint.yaml"
    joint.write_text(DEMO_MAP.read_text() + "limits:\n  target_position: {min: -2.0, max: 3.0}\n")
    f = tmp_path / "net.yaml"
    f.write_text(
        "cycle_time_us: 1000\nreceive_timeout_us: 500\nbuses:\n"
        f"  - {{name: legs, type: ethercat, interface: sim, slaves: [{{name: 'j{{i}}', map: '{joint}', count: 3}}]}}\n"
    )
    with open_network(f, backend="sim", clock=VirtualClock()) as net:
        op = net.bring_up()
        out = op["legs"].outputs
        mon = Monitor(op)
        op.exchange()
        assert [s["last_clamp"] for s in mon.snapshot()["buses"][0]["slaves"]] == [None] * 3
        out["target_position"][1] = 1e12
        op.exchange()
        first = mon.snapshot()["buses"][0]["slaves"][1]["last_clamp"]
        assert (first["reason"], first["asked"], first["sent"]) == ("RANGE", 1e12, pytest.approx(3.0))
        out["target_position"][1] = float("nan")
        op.exchange()
        slaves = mon.snapshot()["buses"][0]["slaves"]
        assert slaves[0]["last_clamp"] is None and slaves[2]["last_clamp"] is None
        c = slaves[1]["last_clamp"]
        assert (c["channel"], c["reason"], c["axis"], c["cycle"]) == ("target_position", "NAN", 1, 2)
        assert c["sent"] == pytest.approx(3.0)  # NaN keeps the value sent last: the window's edge
        text = io.StringIO()
        Console(file=text, width=240, force_terminal=False).print(mon.render())
        shown = text.getvalue()
        assert "last clamp" in shown and "target_position NAN: asked nan, sent 3 (cycle 2)" in shown, shown
