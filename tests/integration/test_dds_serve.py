"""``fieldbus serve`` on the sim emulator and its clients, each in its own process, over DDS on loopback.

Every assertion about the command deadline is in the served bus's cycles (the
cycle numbers and command ages in its published states), never in wall time.
The ROS 2 peer test is judged with a peer that imports cyclonedds and the
message definitions only, not fieldbus.

The bus counts its cycles on the wall clock (1 kHz), so a client process that
a loaded machine stalls for longer than a deadline is, rightly, held or
stopped. The deadlines here are long enough that only the test's own kill or
SIGSTOP reaches them (500 / 2000 cycles; 200 / 1000 for the stalled client),
and tests that are not about the deadline run without one in reach
(``NO_DEADLINE``).
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import select
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import fieldbus.remote
from fieldbus.cli import main
from fieldbus.dds.gate import ClaimError, GateState
from fieldbus.dds.participant import interface_config
from fieldbus.platform.capabilities import fifo_refused

HERE = Path(__file__).resolve().parent / "dds"
DEMO_JOINT = Path(fieldbus.__file__).resolve().parent / "data" / "demo_joint.yaml"
HOLD_AFTER, STOP_AFTER = 500, 2000
NO_DEADLINE = {"hold_after": 60_000, "stop_after": 120_000}  # a minute: requests between commands take time
LOOPBACK = interface_config("lo")
assert LOOPBACK is not None
# the served cycle at SCHED_FIFO where the machine allows it: at normal priority a loaded machine starves
# it past the emulated drives' 100 ms SyncManager watchdog now and then, and the bus latches its safe stop
RT_PRIORITY = 20
REALTIME = [] if fifo_refused(RT_PRIORITY) else ["--rt-priority", str(RT_PRIORITY)]


def _domain(salt: int) -> int:
    """A DDS domain of this test run's own: other runs on the machine use others."""
    return 1 + (os.getpid() * 7 + salt) % 200


def _read_line(proc: subprocess.Popen[str], timeout_s: float) -> dict[str, object]:
    """The next JSON line of ``proc``'s stdout; fails with its stderr when none comes."""
    assert proc.stdout is not None
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        ready, _, _ = select.select([proc.stdout], [], [], 0.2)
        if ready:
            line = proc.stdout.readline()
            if line.strip().startswith("{"):
                return dict(json.loads(line))
            if not line and proc.poll() is not None:
                break
    err = proc.stderr.read() if proc.stderr is not None and proc.poll() is not None else "(still running)"
    pytest.fail(f"no JSON line from {proc.args!r} within {timeout_s} s; stderr: {err}")


def _stop(proc: subprocess.Popen[str]) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


@pytest.fixture
def env() -> dict[str, str]:
    return {**os.environ, "CYCLONEDDS_URI": LOOPBACK}


def _network(path: Path, interface: str, receive_timeout_us: int, drive_map: Path = DEMO_JOINT) -> Path:
    """3 CiA 402 joints of ``drive_map`` (the demo's) at 1 kHz on one EtherCAT bus at ``interface``."""
    path.write_text(
        f"name: robot\ncycle_time_us: 1000\nreceive_timeout_us: {receive_timeout_us}\nbuses:\n"
        f"  - name: joints\n    type: ethercat\n    interface: {interface}\n"
        f"    slaves: [{{name: 'j{{i}}', map: {json.dumps(str(drive_map))}, count: 3}}]\n"
    )
    return path


@contextlib.contextmanager
def _serve(
    net: Path,
    domain: int,
    env: dict[str, str],
    *extra: str,
    hold_after: int = HOLD_AFTER,
    stop_after: int = STOP_AFTER,
) -> Iterator[subprocess.Popen[str]]:
    """``fieldbus serve NET`` in its own process until the block ends; yields it once it is ready."""
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "fieldbus",
            "serve",
            str(net),
            "--domain",
            str(domain),
            "--interface",
            "lo",
            "--hold-after",
            str(hold_after),
            "--stop-after",
            str(stop_after),
            "--json",
            *REALTIME,
            *extra,
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    try:
        ready = _read_line(proc, 60)
        assert ready["ready"] is True and ready["domain"] == domain
        assert ready["realtime"]["refused"] == [], ready  # only asked for where the machine allows it
        yield proc
    finally:
        _stop(proc)


@pytest.fixture
def served(tmp_path: Path, env: dict[str, str], request: pytest.FixtureRequest) -> Iterator[int]:
    """``fieldbus serve`` on 3 emulated CiA 402 joints (sim backend) at 1 kHz; yields its DDS domain."""
    domain = _domain(len(request.node.name))
    with _serve(_network(tmp_path / "robot.yaml", "sim", 500), domain, env, "--backend", "sim"):
        yield domain


def _client(domain: int, client: str, cycles: int, env: dict[str, str], *extra: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, str(HERE / "remote_client.py"), "robot", str(domain), client, str(cycles), *extra],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )


def test_trajectory_from_another_process_and_a_second_controller_is_refused(
    served: int, env: dict[str, str]
) -> None:
    proc = _client(served, "controller-a", 1500, env)
    try:
        assert _read_line(proc, 60) == {"commanding": True}
        with fieldbus.remote.connect(
            "robot", domain=served, interface="lo", client_id="controller-b"
        ) as other:
            with pytest.raises(ClaimError, match="controller-a"):
                other.claim("joints")
            with pytest.raises(ClaimError):
                other.request("enable", "joints")
            # what B sees: the same dtypes as in-process, and A's commands being applied
            assert other["joints"].inputs.values.dtype["position_actual_value"] == np.float64
            res = other.exchange(deadline_s=2.0)
            assert res.gate["joints"] in (GateState.COMMANDED, GateState.HOLD)
            assert other["joints"].state.owner == "controller-a"
        summary = _read_line(proc, 120)
    finally:
        _stop(proc)
    assert summary["cycles"] == 1500
    assert summary["drive_state"] == [4, 4, 4]  # OPERATION ENABLED throughout
    assert "SAFE_STOP" not in summary["gates"]
    # the joints followed the sine (1 - cos) of 0.5 rad: up to ~1 rad in 1.5 s, one cycle behind
    assert float(summary["span_rad"]) > 0.9
    assert float(summary["max_error_rad"]) < 0.05


def _kill_and_see_hold_then_safe_stop(op: fieldbus.remote.Remote, proc: subprocess.Popen[str]) -> None:
    """Kill the commanding client ``proc``; from ``op``'s states (a watcher), in the bus's cycles: the
    gate stays COMMANDED until ``HOLD_AFTER`` cycles after the last command, HOLD until ``STOP_AFTER``,
    then SAFE_STOP (latched, the drives leave OPERATION ENABLED)."""
    for _ in range(50):
        op.exchange(deadline_s=1.0)
    proc.kill()  # no goodbye: the controller is gone
    proc.wait()
    seen: list[tuple[int, GateState, int, list[int]]] = []
    for _ in range(20 * STOP_AFTER):
        op.exchange(deadline_s=1.0)
        seen.append(_gate_of(op))
        if seen[-1][1] is GateState.SAFE_STOP and seen[-1][0] > seen[0][0] + STOP_AFTER + 200:
            break
    _assert_hold_then_safe_stop(seen, HOLD_AFTER, STOP_AFTER)


def _gate_of(op: fieldbus.remote.Remote) -> tuple[int, GateState, int, list[int]]:
    """The newest state's (cycle, gate, command age, drive states)."""
    st = op["joints"].state
    return int(st.cycle), GateState(st.gate), int(st.command_age), list(st.drive_state)


def _assert_hold_then_safe_stop(
    seen: list[tuple[int, GateState, int, list[int]]], hold_after: int, stop_after: int
) -> None:
    """From states seen after the owner's last command (cycle, gate, age, drive states), in bus cycles:
    COMMANDED until ``hold_after`` cycles after it, HOLD until ``stop_after``, then SAFE_STOP, latched
    with the drives out of OPERATION ENABLED."""
    # the cycle of the last command, from every state after it: cycle - age (ages count bus cycles)
    after = [s for s in seen if s[1] is not GateState.COMMANDED]
    assert after, "the gate never left COMMANDED"
    last = {c - a for c, g, a, _ in after if g is not GateState.SAFE_STOP}
    assert len(last) == 1, f"inconsistent ages: {sorted(last)}"
    (last_cmd,) = last
    for cycle, gate, age, _ in after:
        if cycle - last_cmd < hold_after:
            assert gate is GateState.COMMANDED
        elif cycle - last_cmd < stop_after:
            assert gate is GateState.HOLD, (cycle, gate, age)
        else:
            assert gate is GateState.SAFE_STOP, (cycle, gate, age)
            assert age == stop_after  # latched: the age stops where the deadline fired
    assert any(g is GateState.HOLD for _, g, _, _ in after)
    assert seen[-1][1] is GateState.SAFE_STOP
    assert all(s != 4 for s in seen[-1][3]), "the safe stop left an axis in OPERATION ENABLED"


def test_killed_controller_hold_then_safe_stop_in_cycles_then_explicit_clear(
    served: int, env: dict[str, str]
) -> None:
    proc = _client(served, "controller-a", 0, env)
    try:
        assert _read_line(proc, 60) == {"commanding": True}
        with fieldbus.remote.connect("robot", domain=served, interface="lo", client_id="watcher") as op:
            _kill_and_see_hold_then_safe_stop(op, proc)
            # a restarted controller: may claim (the owner's deadline fired), must clear before enabling
            op.claim("joints")
            with pytest.raises(fieldbus.remote.RemoteError, match="clear_safe_stop"):
                op.request("enable", "joints")
            for _ in range(STOP_AFTER // 4):
                assert op.exchange(deadline_s=1.0).gate["joints"] is GateState.SAFE_STOP  # still latched
            op.clear_safe_stop("joints")
            held = op["joints"].inputs["position_actual_value"].copy()
            assert op.exchange(deadline_s=1.0).gate["joints"] is GateState.COMMANDED  # commands count again
            op.enable("joints")
            assert op["joints"].drive_state.tolist() == [4, 4, 4]
            # the claim's first command was the measured position: enabling did not move the joints
            assert np.allclose(op["joints"].inputs["position_actual_value"], held, atol=1e-3)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


@pytest.mark.veth
def test_over_veth_a_client_process_runs_the_trajectory_then_killed_hold_then_safe_stop(
    ethercat_emulator: Any, tmp_path: Path, env: dict[str, str]
) -> None:
    """The same service on EtherCAT: real pysoem frames over a veth pair to the emulated slaves."""
    emu = ethercat_emulator([DEMO_JOINT], count=3)
    domain = _domain(101)
    # a 15 ms receive time-out: the emulator shares a loaded machine (timing is not the point here)
    with _serve(_network(tmp_path / "robot.yaml", emu.iface, 15_000), domain, env) as server:
        proc = _client(domain, "controller-a", 1500, env, "--keep-going")
        try:
            assert _read_line(proc, 60) == {"commanding": True}
            summary = _read_line(proc, 180)
            assert summary["cycles"] == 1500 and summary["drive_state"] == [4, 4, 4], summary
            assert "SAFE_STOP" not in summary["gates"], summary
            assert float(summary["span_rad"]) > 0.9, summary
            assert float(summary["max_error_rad"]) < 0.05, summary
            with fieldbus.remote.connect("robot", domain=domain, interface="lo", client_id="watcher") as op:
                assert op["joints"].state.owner == "controller-a"
                _kill_and_see_hold_then_safe_stop(op, proc)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        _stop(server)
        report = _read_line(server, 30)
    assert report["groups"]["joints"]["gate"] == "SAFE_STOP", report
    assert report["buses"][0]["type"] == "ethercat", report  # pysoem's frames, not the sim backend


def test_a_stalled_controller_hold_then_safe_stop_on_the_deadline_and_no_command_after_it(
    tmp_path: Path, env: dict[str, str]
) -> None:
    """A controller process frozen for >= 200 ms (SIGSTOP: a stall of the whole process, as a long gc
    pause or a slow policy step) while a watcher reads the states: in the bus's cycles the gate holds at
    hold_after and safe-stops at stop_after, the bus keeps counting cycles throughout, and the commands
    the controller sends once it wakes are not applied (the latch stays until an explicit clear)."""
    hold_after, stop_after = 200, 1000
    domain = _domain(202)
    net = _network(tmp_path / "robot.yaml", "sim", 500)
    with _serve(net, domain, env, "--backend", "sim", hold_after=hold_after, stop_after=stop_after):
        proc = _client(domain, "controller-a", 0, env)
        try:
            assert _read_line(proc, 60) == {"commanding": True}
            with fieldbus.remote.connect("robot", domain=domain, interface="lo", client_id="watcher") as op:
                for _ in range(50):
                    assert op.exchange(deadline_s=1.0).gate["joints"] is GateState.COMMANDED
                os.kill(proc.pid, signal.SIGSTOP)
                stalled_at = time.monotonic()
                seen = [_gate_of(op)]
                # frozen for at least 200 ms and until the bus has counted past the deadline (cycles)
                while time.monotonic() - stalled_at < 0.2 or seen[-1][0] < seen[0][0] + stop_after + 50:
                    op.exchange(deadline_s=1.0)
                    seen.append(_gate_of(op))
                os.kill(proc.pid, signal.SIGCONT)
                _assert_hold_then_safe_stop(seen, hold_after, stop_after)
                applied = int(op["joints"].state.command_sequence)
                woke = [op.exchange(deadline_s=1.0) for _ in range(200)]
                st = op["joints"].state
                # the controller runs again (its sequence numbers reach the gate), but nothing is applied
                assert st.owner == "controller-a" and st.gate == GateState.SAFE_STOP
                assert int(st.command_sequence) == applied
                assert all(r.gate["joints"] is GateState.SAFE_STOP for r in woke)
                assert int(st.cycle) > seen[-1][0]
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()


def test_a_ros2_peer_without_fieldbus_reads_joint_states_and_commands(
    served: int, env: dict[str, str]
) -> None:
    peer = subprocess.run(
        [sys.executable, str(HERE / "ros2_peer.py"), "robot", "joints", str(served), "0.2"],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )
    assert peer.returncode == 0, peer.stderr
    out = json.loads(peer.stdout.strip().splitlines()[-1])
    assert out["fieldbus_imported"] == []
    assert out["names"] == ["j0", "j1", "j2"]
    assert out["answers"] == {"claim": [True, ""], "enable": [True, ""]}
    # the joints went to position + 0.2 rad (within the encoder's resolution)
    assert np.allclose(out["after"], out["goal"], atol=1e-3), out
    assert not np.allclose(out["before"], out["goal"], atol=0.1)


@contextlib.contextmanager
def _served_with_homing(tmp_path: Path, env: dict[str, str], method: int) -> Iterator[fieldbus.remote.Remote]:
    """A served bus whose drives' map sets homing method ``method`` (0x6098); a claimed, enabled client."""
    drive_map = tmp_path / "joint_homing.yaml"
    drive_map.write_text(DEMO_JOINT.read_text() + f"\nhoming:\n  method: {method}\n  timeout_ms: 2000\n")
    domain = _domain(300 + method)
    with (
        _serve(
            _network(tmp_path / "robot.yaml", "sim", 500, drive_map),
            domain,
            env,
            "--backend",
            "sim",
            **NO_DEADLINE,
        ),
        fieldbus.remote.connect("robot", domain=domain, interface="lo", client_id="homer") as op,
    ):
        op.claim("joints")
        op.enable("joints")
        yield op


@pytest.mark.parametrize("method", [37, 1])
def test_home_request_answered_when_homing_ends_with_success_or_the_failed_axes(
    tmp_path: Path, env: dict[str, str], method: int
) -> None:
    """37 (home on the current position) the emulated drives implement; 1 they refuse (bit 13)."""
    with _served_with_homing(tmp_path, env, method) as op:
        legs = op["joints"]
        if method == 37:
            done = op.home("joints")
            assert done["phases"] == ["DONE"] * 3 and min(done["cycles"]) >= 2
        else:
            with pytest.raises(fieldbus.remote.RemoteError, match=r"did not end: j0: FAILED, j1: FAILED"):
                op.home("joints")
        # back in CSP, still enabled, and commands count again (the deadline was paused while homing)
        assert op.exchange(deadline_s=1.0).gate["joints"] is GateState.COMMANDED
        assert legs.inputs["modes_of_operation_display"].tolist() == [8, 8, 8]
        assert legs.drive_state.tolist() == [4, 4, 4]
        with (
            fieldbus.remote.connect("robot", domain=op.participant.domain_id, interface="lo") as other,
            pytest.raises(ClaimError, match="homer"),
        ):
            other.home("joints")


def test_mode_and_sdo_requests_answered_with_success_or_the_error(
    tmp_path: Path, env: dict[str, str]
) -> None:
    with _served_with_homing(tmp_path, env, 37) as op:
        legs = op["joints"]
        assert [op.sdo_read("joints", a, 0x6098, 0) for a in legs.axes] == [bytes([37])] * 3  # from bring-up
        op.sdo_write("joints", "j1", 0x6098, 0, bytes([35]))
        assert [op.sdo_read("joints", a, 0x6098, 0) for a in legs.axes] == [bytes([n]) for n in (37, 35, 37)]
        with pytest.raises(fieldbus.remote.RemoteError, match="0x06020000"):  # no such object: the abort
            op.sdo_read("joints", "j1", 0x2FFF, 0)
        with pytest.raises(fieldbus.remote.RemoteError, match="no axis 'j9'"):
            op.sdo_read("joints", "j9", 0x6098, 0)
        op.set_mode("joints", "CSV")
        assert legs.inputs["modes_of_operation_display"].tolist() == [9, 9, 9]
        op.set_mode("joints", 8)
        assert legs.inputs["modes_of_operation_display"].tolist() == [8, 8, 8]
        assert op.exchange(deadline_s=1.0).gate["joints"] is GateState.COMMANDED
        with pytest.raises(fieldbus.remote.RemoteError, match="unknown mode 'bogus'"):
            op.set_mode("joints", "bogus")
        with fieldbus.remote.connect("robot", domain=op.participant.domain_id, interface="lo") as other:
            assert other.sdo_read("joints", "j2", 0x6098, 0) == bytes([37])  # reading needs no claim
            with pytest.raises(ClaimError, match="homer"):
                other.sdo_write("joints", "j2", 0x6098, 0, bytes([35]))
            with pytest.raises(ClaimError, match="homer"):
                other.set_mode("joints", "CSV")


def test_a_ros2_service_client_without_fieldbus_calls_trigger_setbool_and_sdo_read(
    served: int, env: dict[str, str]
) -> None:
    """ROS 2 services as rmw_cyclonedds lays them out (rq/rr topics, request header echoed), called by a
    client that imports cyclonedds only: Trigger refused before the claim, then SetBool claim, Trigger
    enable (the drive's own statusword, read by the SdoRead service, shows OPERATION ENABLED), commands
    under the client id the claim named (the joints go there), SetMode
    (the drive's 0x6061 shows it; an unknown mode is refused)."""
    peer = subprocess.run(
        [sys.executable, str(HERE / "ros2_service_client.py"), "robot", "joints", str(served)],
        capture_output=True,
        text=True,
        env=env,
        timeout=180,
    )
    assert peer.returncode == 0, peer.stderr
    out = json.loads(peer.stdout.strip().splitlines()[-1])
    assert out["fieldbus_imported"] == []
    calls = out["calls"]
    ok, message = calls["enable_unclaimed"]
    assert not ok and message.startswith("ClaimError: ") and "not claimed" in message
    ok, message = calls["claim"]
    assert ok and re.search(r"claimed as client 'ros2-[0-9a-f]+'", message), message
    assert calls["enable"] == [True, ""]  # answered once the drives are enabled
    ok, message = calls["reset_faults_unclaimed"]
    assert not ok and message.startswith("ClaimError: ")
    assert calls["reset_faults"] == [True, '{"re_armed": []}']  # no joint had given up
    ok, _, statusword = calls["statusword"]
    assert ok and statusword[0] & 0x6F == 0x27, statusword  # OPERATION ENABLED, as the drive reports it
    moved = out["moved"]  # commanded under the client id the claim named: the joints went there
    assert np.allclose(moved["after"], moved["goal"], atol=1e-3), moved
    assert not np.allclose(moved["before"], moved["goal"], atol=0.1)
    assert calls["sdo_read"] == [True, "", [8]]  # 0x6060: CSP
    ok, message, _ = calls["sdo_read_bad"]
    assert not ok and "no axis 'j9'" in message
    assert calls["set_mode_csv"] == [True, '{"mode": "CSV"}']
    assert calls["mode_display_csv"] == [True, "", [9]]  # the drive shows CSV (0x6061)
    ok, message = calls["set_mode_bad"]
    assert not ok and "unknown mode 'bogus'" in message
    assert calls["set_mode_8"] == [True, '{"mode": "CSP"}']
    assert calls["disable"] == [True, ""] and calls["release"] == [True, ""]
    with fieldbus.remote.connect("robot", domain=served, interface="lo", client_id="watcher") as op:
        assert op["joints"].state.owner == ""  # released
        assert all(s != 4 for s in op["joints"].drive_state.tolist())  # disabled


def _monitor(domain: int, *extra: str) -> list[str]:
    return ["monitor", "--dds", "--namespace", "robot", "--domain", str(domain), "--interface", "lo", *extra]


def test_monitor_dds_shows_the_served_joints_drive_states_gate_and_verdicts(
    tmp_path: Path, env: dict[str, str], capsys: pytest.CaptureFixture[str]
) -> None:
    served = _domain(505)
    net = _network(tmp_path / "robot.yaml", "sim", 500)
    with (
        _serve(net, served, env, "--backend", "sim", **NO_DEADLINE),  # the client waits for the monitor
        fieldbus.remote.connect("robot", domain=served, interface="lo", client_id="mover") as op,
    ):
        op.claim("joints")
        op.enable("joints")
        for _ in range(20):
            op.exchange(deadline_s=1.0)
        assert main(_monitor(served, "--once", "--json")) == 0
        snap = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
        assert main(_monitor(served, "--refreshes", "2", "--rate", "10")) == 0
        text = capsys.readouterr().out
    (group,) = snap["groups"]
    assert group["name"] == "joints" and group["owner"] == "mover" and not group["safe_stop"]
    assert group["gate"] in ("COMMANDED", "HOLD") and group["command_sequence"] > 0
    assert [a["name"] for a in group["axes"]] == ["j0", "j1", "j2"]
    assert [a["drive_state"] for a in group["axes"]] == ["operation enabled"] * 3
    assert all(a["fresh"] and a["position"] is not None for a in group["axes"])
    bus = next(s for s in snap["diagnostics"] if s["hardware_id"] == "sim")
    assert (bus["name"], bus["level"], bus["message"]) == ("fieldbus/bus/joints", "OK", "OK")
    assert bus["values"]["misses"] == "0" and "safe_stops" in bus["values"]
    # the text view, refreshed twice: the joints with their drive states, the gate, the bus's verdict
    assert text.count("group joints: cycle") == 2 and text.count("owner mover") == 2
    assert text.count("operation enabled") == 6 and "fieldbus/bus/joints [OK] OK" in text


def test_monitor_dds_without_a_served_bus_is_one_clear_error(
    env: dict[str, str], capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(_monitor(_domain(404), "--once", "--timeout", "1")) == 1
    err = capsys.readouterr().err
    assert "no reply to 'describe' from namespace 'robot'" in err and "Traceback" not in err


def _adversary(mode: str, domain: int, env: dict[str, str]) -> subprocess.Popen[str]:
    """``dds/adversary.py MODE``: a client made with cyclonedds only (no fieldbus import)."""
    return subprocess.Popen(
        [sys.executable, str(HERE / "adversary.py"), mode, "robot", "joints", str(domain)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )


def _last_line(proc: subprocess.Popen[str], timeout_s: float) -> dict[str, Any]:
    out, err = proc.communicate(timeout=timeout_s)
    assert proc.returncode == 0, err
    return dict(json.loads(out.strip().splitlines()[-1]))


def test_an_independent_client_cannot_move_a_joint_by_forging_the_owners_client_id(
    served: int, env: dict[str, str]
) -> None:
    """Two DDS participants: the owner holds the joints; the other sends under the owner's client_id with
    sequence numbers a million higher and +0.06 rad. The bus applies the owner's commands only."""
    res = _last_line(_adversary("forge", served, env), 120)
    assert res["owner"] == "owner"
    # the owner's own (the forger's start at a million), its last ones perhaps still in flight; none of
    # the owner's was dropped as stale behind the forger's higher numbers
    assert res["owner_sequence"] - 50 < res["applied"] <= res["owner_sequence"], res
    assert res["refused"] >= 100 and res["dropped"] == 0
    assert np.allclose(res["after"], res["before"], atol=2e-3), res  # the forger moved nothing


def test_an_independent_client_sending_only_nan_is_held_then_safe_stopped_on_the_deadline(
    served: int, env: dict[str, str]
) -> None:
    """After one valid command only NaN: the deadline runs as if nothing came (NaN is no sign of life)."""
    res = _last_line(_adversary("nan", served, env), 180)
    applied = [q for _, _, _, q, _ in res["seen"]]
    first = applied.index(res["valid_sequence"])  # states from before the valid command: none applied yet
    assert set(applied[:first]) <= {0} and set(applied[first:]) == {res["valid_sequence"]}  # no NaN applied
    seen = [(int(c), GateState(g), int(age), ds) for c, g, age, _, ds in res["seen"][first:]]
    _assert_hold_then_safe_stop(seen, HOLD_AFTER, STOP_AFTER)  # in the bus's cycles, as if nothing came
    assert res["refused"] > len(seen) // 2  # counted (a best-effort sample may be lost, a count be late)


@pytest.mark.parametrize("owner_mode", ["commander", "silent"])
def test_an_owner_killed_with_sigkill_leaves_the_group_claimable_on_the_deadline(
    served: int, env: dict[str, str], owner_mode: str
) -> None:
    """A cyclonedds-only owner is killed (SIGKILL: no release, no goodbye) while commanding, or after its
    enable before any command; another cyclonedds-only client asking to claim is refused only while the
    deadline (counted from the last command, or from the enable) has not fired, then gets the group."""
    owner = _adversary(owner_mode, served, env)
    claimer = None
    try:
        assert _read_line(owner, 60) == {"commanding": True}
        claimer = _adversary("claimer", served, env)
        assert "refused_after" in _read_line(claimer, 60)  # refused while the owner lives
        owner.kill()
        owner.wait()
        res = _last_line(claimer, 120)
    finally:
        for p in (owner, claimer):
            if p is not None and p.poll() is None:
                p.kill()
                p.wait()
    assert GateState(res["gate"]) is GateState.SAFE_STOP  # the dead owner's deadline latched
    last = int(res["last_command_cycle"])
    assert res["refused"] and all(before < last + STOP_AFTER for before, _ in res["refused"]), res
    assert all("commanded by client 'commander'" in why for _, why in res["refused"])


def _policies(pid: int) -> dict[int, tuple[int, int]]:
    """Every thread of process ``pid``: (scheduling policy, real-time priority), by thread id."""
    out = {}
    for tid in (int(t) for t in os.listdir(f"/proc/{pid}/task")):
        with contextlib.suppress(ProcessLookupError):
            out[tid] = (os.sched_getscheduler(tid), os.sched_getparam(tid).sched_priority)
    return out


_SET_UP_CHILD = """
import json, os, sys
from fieldbus.cli import main
from fieldbus.dds.server import BusServer
from fieldbus.network import Network
seen = {}
def policy():
    return [os.sched_getscheduler(0), os.sched_getparam(0).sched_priority]
def topics(self, *a, **k):
    seen["topics"] = policy()
    real_init(self, *a, **k)
def bring_up(self, *a, **k):
    seen["bring_up"] = policy()
    return real_bring_up(self, *a, **k)
real_init, real_bring_up = BusServer.__init__, Network.bring_up
BusServer.__init__, Network.bring_up = topics, bring_up
code = main(sys.argv[1:])
print(json.dumps(seen))
sys.exit(code)
"""


def test_at_rt_priority_the_topics_are_made_at_normal_priority_and_the_bring_up_at_the_cycles(
    tmp_path: Path, env: dict[str, str]
) -> None:
    """Made at SCHED_FIFO, the participant, network and topics (seconds of Python) used most of the
    kernel's real-time budget for their second (sched_rt_runtime_us, 950 ms of 1 s on a CPU: 832 ms
    seen) and the first cycles could be throttled: a 38 ms gap at cycle 19. Now they are made at normal
    priority; the bring-up and the cycles run at --rt-priority, Cyclone's threads one below."""
    if why := fifo_refused(RT_PRIORITY):
        pytest.skip(f"this machine refuses: {why}")
    net = _network(tmp_path / "robot.yaml", "sim", 500)
    args = ["serve", str(net), "--backend", "sim", "--domain", str(_domain(95)), "--interface", "lo"]
    args += ["--json", "--cycles", "20", "--rt-priority", str(RT_PRIORITY)]
    run = subprocess.run(
        [sys.executable, "-c", _SET_UP_CHILD, *args], capture_output=True, text=True, env=env, timeout=120
    )
    assert run.returncode == 0, run.stderr
    ready, report, seen = (json.loads(line) for line in run.stdout.splitlines())
    assert seen == {"topics": [os.SCHED_OTHER, 0], "bring_up": [os.SCHED_FIFO, RT_PRIORITY]}
    applied = ready["realtime"]["applied"]
    assert applied[0] == f"SCHED_FIFO priority {RT_PRIORITY}"
    assert f"other thread(s) below the cycle: SCHED_FIFO priority {RT_PRIORITY - 1}" in applied[1], applied
    assert int(applied[1].split()[0]) >= 3  # Cyclone's receive, event and delivery threads
    assert report["cycles"] == 20


@pytest.mark.parametrize("pinned", [False, True], ids=["unpinned", "cpu"])
def test_at_rt_priority_the_cycle_thread_alone_has_it_and_the_dds_threads_are_one_below(
    tmp_path: Path, env: dict[str, str], pinned: bool
) -> None:
    """Cyclone's receive and event threads start after the switch to SCHED_FIFO and inherit the cycle's
    priority (and, with --cpu, its one CPU); at the same priority a running one is not preempted by the
    cycle when its deadline comes. Served and commanded, the cycle thread (serve's main thread) is the only
    one at ``--rt-priority``; Cyclone's threads are one below (still above normal work, so commands are in
    the reader in time), and with ``--cpu`` only the cycle thread is pinned."""
    if why := fifo_refused(RT_PRIORITY):
        pytest.skip(f"this machine refuses: {why}")
    allowed = os.sched_getaffinity(0)
    if pinned and len(allowed) < 2:
        pytest.skip("one CPU: a pinned thread and an unpinned one cannot be told apart")
    cpu = max(allowed)
    domain = _domain(91 + pinned)
    net = _network(tmp_path / "robot.yaml", "sim", 500)
    extra = ["--cpu", str(cpu)] if pinned else []
    with (
        _serve(net, domain, env, "--backend", "sim", *extra, **NO_DEADLINE) as proc,
        fieldbus.remote.connect("robot", domain=domain, interface="lo", client_id="rt") as op,
    ):
        op.claim("joints")
        op.enable("joints")
        for _ in range(50):  # commanded: any thread made while serving exists now
            op.exchange(deadline_s=1.0)
        policies = _policies(proc.pid)
        cpus = {t: os.sched_getaffinity(t) for t in policies}
    assert policies.pop(proc.pid) == (os.SCHED_FIFO, RT_PRIORITY)
    realtime = {os.SCHED_FIFO, os.SCHED_RR}
    at_or_above = {t: p for t, p in policies.items() if p[0] in realtime and p[1] >= RT_PRIORITY}
    assert at_or_above == {}, f"threads at the cycle's priority or above: {at_or_above}"
    below = [t for t, p in policies.items() if p == (os.SCHED_FIFO, RT_PRIORITY - 1)]
    assert len(below) >= 3, policies  # Cyclone's receive, event and delivery threads
    assert cpus.pop(proc.pid) == ({cpu} if pinned else allowed)
    assert all(c == allowed for c in cpus.values()), cpus  # serve's other threads on every CPU
