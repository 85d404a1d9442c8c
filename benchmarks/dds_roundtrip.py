"""Command-to-state round trip at 1 kHz: the controller in another process over DDS, and in-process.

    python benchmarks/dds_roundtrip.py [--cycles N] [--axes N] [--json]

Remote: ``fieldbus serve`` (sim emulator, loopback, its own DDS domain) in a
child process; this process runs the demo's sine through ``fieldbus.remote``:
per cycle, write the target, ``exchange()`` (send the command, wait for the
state that applied it). Round trip = command written -> that state taken.
In-process: the same sine on the same network with ``op.exchange()`` paced by
``fieldbus.run_cycles``; its "round trip" is the exchange() call (the command
is on the wire in the same call). Misses: remote exchanges whose state did not
come within the deadline (5 cycles); in-process cycles that were not fresh.
Wall-clock figures: they depend on the machine and its load (say which).
"""

from __future__ import annotations

import argparse
import json
import math
import os
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


def remote(net: Path, cycles: int) -> dict[str, Any]:
    domain = 1 + os.getpid() % 200
    env = {**os.environ, "CYCLONEDDS_URI": interface_config("lo") or ""}
    server = subprocess.Popen(
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
            "100000",
            "--hold-after",
            "50000",
        ],
        stdout=subprocess.PIPE,
        text=True,
        env=env,
    )
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


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cycles", type=int, default=5000)
    ap.add_argument("--axes", type=int, default=12)
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="fieldbus-bench-") as tmp:
        net = _network(Path(tmp), a.axes)
        out = {
            "axes": a.axes,
            "rate_hz": 1000,
            "cpus": os.cpu_count(),
            "load_avg": os.getloadavg()[0],
            "in_process": in_process(net, a.cycles),
            "remote": remote(net, a.cycles),
        }
    if a.json:
        print(json.dumps(out))
    else:
        for name in ("in_process", "remote"):
            r = out[name]
            print(
                f"{name:10s} p50 {r['p50_us']} us  p99 {r['p99_us']} us  max {r['max_us']} us  misses {r['misses']}"
            )
        print(f"(load average {out['load_avg']:.1f} on {out['cpus']} CPUs)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
