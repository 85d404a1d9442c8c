"""Command-to-state round trip at 1 kHz: the controller in another process over DDS, and in-process.

    python benchmarks/dds_roundtrip.py [--cycles N] [--axes N] [--json] [--stall-only]

Remote: ``fieldbus serve`` (sim emulator, loopback, its own DDS domain) in a
child process; this process runs the demo's sine through ``fieldbus.remote``:
per cycle, write the target, ``exchange()`` (send the command, wait for the
state that applied it). Round trip = command written -> that state taken.
In-process: the same sine on the same network with ``op.exchange()`` paced by
``fieldbus.run_cycles``; its "round trip" is the exchange() call (the command
is on the wire in the same call). Misses: remote exchanges whose state did not
come within the deadline (5 cycles); in-process cycles that were not fresh.

Free-running: a client on its own 1 kHz clock sends a command every period without waiting
(``Remote.send``) and polls the states (``Remote.poll``): latency = sent -> the first state showing it
applied; commands the bus never applied (superseded by a newer one before a cycle took them) counted.

Stall: a controller process commands the served bus for 1 s, sleeps 200 ms,
commands again; this process watches the published states (no claim) and
counts the bus's cycle numbers per wall second before, during and after the
stall (their ratio is the point: 1.0 = the stall costs the bus nothing), and
the cycles from the last command to HOLD and to SAFE_STOP.
Wall-clock figures: they depend on the machine and its load (say which).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import select
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

import fieldbus
import fieldbus.remote
from fieldbus.dds.participant import interface_config

DEMO_JOINT = Path(fieldbus.__file__).resolve().parent / "data" / "demo_joint.yaml"


def _percentiles(ns: list[int]) -> dict[str, float]:
    a = np.asarray(ns, dtype=np.float64) / 1e3
    return {
        "p50_us": round(float(np.percentile(a, 50)), 1),
        "p99_us": round(float(np.percentile(a, 99)), 1),
        "max_us": round(float(a.max()), 1),
    }


def _network(tmp: Path, axes: int) -> Path:
    net = tmp / "bench.yaml"
    net.write_text(
        "name: bench\ncycle_time_us: 1000\nreceive_timeout_us: 500\nbuses:\n  - name: joints\n    type: ethercat\n"
        f"    interface: sim\n    slaves: [{{name: 'j{{i}}', map: {json.dumps(str(DEMO_JOINT))}, count: {axes}}}]\n"
    )
    return net


RT_PRIORITY = 0  # --rt-priority: the served cycle (and this client) at SCHED_FIFO


def _server(net: Path, domain: int, hold_after: int, stop_after: int) -> subprocess.Popen[str]:
    env = {**os.environ, "CYCLONEDDS_URI": interface_config("lo") or ""}
    rt = ["--rt-priority", str(RT_PRIORITY)] if RT_PRIORITY else []
    return subprocess.Popen(
        [
            sys.executable,
            "-m",
            "fieldbus",
            "serve",
            str(net),
            "--backend",
            "sim",
            "--domain",
            str(domain),
            "--interface",
            "lo",
            "--json",
            "--stop-after",
            str(stop_after),
            "--hold-after",
            str(hold_after),
            *rt,
        ],
        stdout=subprocess.PIPE,
        text=True,
        env=env,
    )


def remote(net: Path, cycles: int) -> dict[str, Any]:
    domain = 1 + os.getpid() % 200
    server = _server(net, domain, 50_000, 100_000)
    try:
        assert server.stdout is not None
        json.loads(server.stdout.readline())  # ready
        op = fieldbus.remote.connect("bench", domain=domain, interface="lo", deadline_s=0.005)
        legs = op["joints"]
        op.claim("joints")
        op.enable("joints")
        rt, skipped = [], 0
        pos, tgt = legs.inputs["position_actual_value"], legs.outputs["target_position"]
        start = pos.copy()
        last_cycle = legs.state.cycle
        for k in range(cycles):
            tgt[:] = start + 0.5 * (1 - math.cos(2 * math.pi * 0.5 * k / 1000))
            res = op.exchange()
            if not res.late:
                rt.append(res.round_trip_ns)
                skipped += max(0, res.cycle - last_cycle - 1)  # bus cycles that got no new command
            last_cycle = res.cycle
        op.close()
    finally:
        server.send_signal(signal.SIGTERM)
        out, _ = server.communicate(timeout=30)
    report = json.loads(out.strip().splitlines()[-1])
    return {
        **_percentiles(rt),
        "misses": op.misses,
        "exchanges": cycles,
        "bus_cycles_without_new_command": skipped,
        "server_missed": report["missed"],
        "server_cycle_us": report["cycle_time_us"],
    }


def free_running(net: Path, cycles: int) -> dict[str, Any]:
    """A client on its own 1 kHz clock: sends a command every period without waiting (``Remote.send``),
    polls the states (``Remote.poll``). Latency = sent -> the first state that shows it applied;
    superseded = commands the bus never applied (a newer one came before its cycle)."""
    domain = 1 + (os.getpid() + 2) % 200
    server = _server(net, domain, 50_000, 100_000)
    try:
        assert server.stdout is not None
        json.loads(server.stdout.readline())  # ready
        op = fieldbus.remote.connect("bench", domain=domain, interface="lo", deadline_s=0.005)
        legs = op["joints"]
        op.claim("joints")
        op.enable("joints")
        tgt, pos = legs.outputs["target_position"], legs.inputs["position_actual_value"]
        start = pos.copy()
        sent: dict[int, int] = {}
        latency: list[int] = []
        applied_seen = 0
        superseded = 0
        period = 1_000_000
        deadline = time.perf_counter_ns()
        for k in range(cycles):  # its own 1 kHz clock; between two sends it waits for states
            tgt[:] = start + 0.5 * (1 - math.cos(2 * math.pi * 0.5 * k / 1000))
            sent[op.send()] = time.perf_counter_ns()
            deadline += period
            while (now := time.perf_counter_ns()) < deadline:
                applied = op.poll(wait_s=(deadline - now) / 1e9)
                now = time.perf_counter_ns()
                if applied > applied_seen:
                    if applied in sent:
                        latency.append(now - sent[applied])
                    superseded += sum(1 for q in range(applied_seen + 1, applied) if q in sent)
                    for q in [q for q in sent if q <= applied]:
                        del sent[q]
                    applied_seen = applied
        op.close()
    finally:
        server.send_signal(signal.SIGTERM)
        server.communicate(timeout=30)
    return {**_percentiles(latency), "commands": cycles, "superseded": superseded, "applied": len(latency)}


def in_process(net: Path, cycles: int) -> dict[str, Any]:
    with fieldbus.open_network(net, backend="sim") as n:
        op = n.bring_up()
        legs = op["joints"]
        ctrl = fieldbus.Cia402Controller(legs.n_axes)
        ctrl.set_goal(fieldbus.Goal.ENABLE)
        sw, cw = legs.inputs["statusword"], legs.outputs["controlword"]
        md, mo = legs.inputs["modes_of_operation_display"], legs.outputs["modes_of_operation"]
        pos, tgt = legs.inputs["position_actual_value"], legs.outputs["target_position"]
        times: list[int] = []
        misses = 0
        state = {"start": None}

        def step(k: int) -> None:
            nonlocal misses
            t0 = time.perf_counter_ns()
            res = op.exchange()
            times.append(time.perf_counter_ns() - t0) if state["start"] is not None else None
            misses += not res.fresh
            ctrl.step(sw, cw, md, mo)
            if state["start"] is None:
                tgt[:] = pos
                if ctrl.all_reached:
                    state["start"] = k
                return
            tgt[:] = pos[0] * 0 + 0.5 * (1 - math.cos(2 * math.pi * 0.5 * (k - state["start"]) / 1000))

        fieldbus.run_cycles(step, op.cycle_time_us, cycles + 500)
    return {**_percentiles(times), "misses": misses, "cycles": len(times)}


STALL_S, HOLD_AFTER, STOP_AFTER = 0.2, 20, 100


def stall_controller(domain: int) -> int:
    """The child: command for 1 s, sleep STALL_S, command for 0.5 s (prints 'stall' as it sleeps)."""
    op = fieldbus.remote.connect("bench", domain=domain, interface="lo", deadline_s=0.05)
    op.claim("joints")
    op.enable("joints")
    for seconds in (1.0, 0.5):
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            op.exchange()
        if seconds == 1.0:
            print("stall", flush=True)
            time.sleep(STALL_S)
    print("done", flush=True)
    return 0


def stall(net: Path) -> dict[str, Any]:
    """The served bus's rate while its controller sleeps STALL_S, from the published cycle numbers."""
    domain = 1 + (os.getpid() + 1) % 200
    server = _server(net, domain, HOLD_AFTER, STOP_AFTER)
    env = {**os.environ, "CYCLONEDDS_URI": interface_config("lo") or ""}
    try:
        assert server.stdout is not None
        json.loads(server.stdout.readline())  # ready
        child = subprocess.Popen(
            [sys.executable, __file__, "--stall-controller", str(domain)],
            stdout=subprocess.PIPE,
            text=True,
            env=env,
        )
        assert child.stdout is not None
        op = fieldbus.remote.connect("bench", domain=domain, interface="lo", deadline_s=0.05)
        seen: list[tuple[float, int, int, int]] = []  # (wall s, cycle, gate, command age)
        marks: dict[str, float] = {}
        while "done" not in marks:
            op.exchange()
            st = op["joints"].state
            seen.append((time.monotonic(), int(st.cycle), int(st.gate), int(st.command_age)))
            if select.select([child.stdout], [], [], 0)[0]:
                line = child.stdout.readline().strip()
                if not line:
                    break
                marks[line] = time.monotonic()
        child.wait(30)
        op.close()
    finally:
        server.send_signal(signal.SIGTERM)
        out, _ = server.communicate(timeout=30)
    report = json.loads(out.strip().splitlines()[-1])

    def rate(t0: float, t1: float) -> float:
        w = [(t, c) for t, c, _, _ in seen if t0 <= t <= t1]
        return (w[-1][1] - w[0][1]) / (w[-1][0] - w[0][0])

    t_stall = marks["stall"]
    before = rate(t_stall - 0.5, t_stall)
    during = rate(t_stall, t_stall + STALL_S)
    hold_at = [c for _, c, g, _ in seen if g == 2]
    stop_at = [(c, a) for _, c, g, a in seen if g == 3]
    return {
        "stall_s": STALL_S,
        "hold_after": HOLD_AFTER,
        "stop_after": STOP_AFTER,
        "bus_cycles_per_s_before": round(before, 1),
        "bus_cycles_per_s_during_stall": round(during, 1),
        "ratio_during_to_before": round(during / before, 3),
        "hold_seen_age_min": min((a for _, _, g, a in seen if g == 2), default=None),
        "safe_stop_age": stop_at[0][1] if stop_at else None,
        "hold_states_seen": len(hold_at),
        "last_command_cycle": min((c - a for _, c, g, a in seen if g == 2), default=None),
        "server_missed": report["missed"],
        "server_cycle_us": report["cycle_time_us"],
    }


def main() -> int:
    if len(sys.argv) == 3 and sys.argv[1] == "--stall-controller":
        return stall_controller(int(sys.argv[2]))
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cycles", type=int, default=5000)
    ap.add_argument("--axes", type=int, default=12)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--stall-only", action="store_true", help="only the 200 ms stalled-controller run")
    ap.add_argument("--rt-priority", type=int, default=0, help="SCHED_FIFO priority of serve and this client")
    a = ap.parse_args()
    global RT_PRIORITY
    RT_PRIORITY = a.rt_priority
    if a.rt_priority:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(a.rt_priority - 1))
    with tempfile.TemporaryDirectory(prefix="fieldbus-bench-") as tmp:
        net = _network(Path(tmp), a.axes)
        out: dict[str, Any] = {
            "axes": a.axes,
            "rate_hz": 1000,
            "cpus": os.cpu_count(),
            "load_avg": os.getloadavg()[0],
            "rt_priority": a.rt_priority,
        }
        if not a.stall_only:
            out["in_process"] = in_process(net, a.cycles)
            out["remote"] = remote(net, a.cycles)
            out["free_running"] = free_running(net, a.cycles)
        out["stall"] = stall(net)
    if a.json or a.stall_only:
        print(json.dumps(out))
    else:
        for name in ("in_process", "remote", "free_running"):
            r = out[name]
            extra = f"superseded {r['superseded']}" if "superseded" in r else f"misses {r['misses']}"
            print(f"{name:12s} p50 {r['p50_us']} us  p99 {r['p99_us']} us  max {r['max_us']} us  {extra}")
        print(f"(load average {out['load_avg']:.1f} on {out['cpus']} CPUs)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
