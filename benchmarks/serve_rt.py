"""The served cycle at SCHED_FIFO beside CPU burners and a 1 kHz client: does it keep its period?

    python benchmarks/serve_rt.py [--seconds 10] [--rt-priority 50] [--burners 2] [--spin-us 30 150]

For each ``--spin-us`` value, side by side on the same load: ``fieldbus serve``
(sim emulator, 3 CiA 402 joints, 1 kHz, loopback, its own DDS domain) at
``--rt-priority``, a client in this process that claims, enables and commands
every cycle through ``fieldbus.remote`` (each exchange waits for the state
that applied it: about 1 kHz), and ``--burners`` processes spinning
``while 1: pass``. Reported per run, from serve's own report: the longest
step (cycle_time_us max) and its p99, overruns, the longest gap between two cycles'
starts, the gaps over 5 ms and the stalls (gaps of 20 periods or more, StallWatch), bus misses and
safe stops; and serve's CPU use while it was commanded (all its threads, from
/proc). ``--veth``: a real EtherCAT bus instead of the sim backend: pysoem's frames over a veth pair to the
emulated drives in their own process (``sim_slaves.ethercat``, SCHED_FIFO 40 where allowed; needs root), so
the served step no longer runs the drives' physics. ``--meter``: first, on the same load, ``cpu_meter.py`` (fixed Python work every millisecond at the same
priority, without fieldbus): how steady the machine's CPU itself is. ``--witness``: beside serve, at its priority, ``wake_witness.py`` (a thread that wakes every millisecond,
as ``cyclictest``, and does 20 µs of work), and for each gap over 5 ms whether the witness woke late or
ran slowly by 1 ms or more during it. ``--trace``: serve runs under ``serve_phases.py``, which times each phase of the served step
(requests, commands, exchange, publish, diagnostics, DDS writes) and reports the longest steps' breakdown. A SCHED_FIFO thread that uses more than sched_rt_runtime_us of every
sched_rt_period_us is throttled for the rest of that period: the point of a
short spin is to stay well below it. Wall-clock figures: they depend on the
machine and its load; the load average is printed with them.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import fieldbus
import fieldbus.remote
from fieldbus.dds.participant import interface_config

DEMO_JOINT = Path(fieldbus.__file__).resolve().parent / "data" / "demo_joint.yaml"


def _cpu_s(pid: int) -> float:
    """utime + stime of process ``pid`` (all threads), s."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _run(
    net: Path,
    domain: int,
    seconds: float,
    priority: int,
    spin_us: int,
    trace: Path | None = None,
    backend: str | None = "sim",
    extra: tuple[str, ...] = (),
    witness: Path | None = None,
    witness_cpu: int | None = None,
    witness_priority: int | None = None,
) -> dict[str, Any]:
    env = {**os.environ, "CYCLONEDDS_URI": interface_config("lo") or ""}
    serve = [sys.executable, "-m", "fieldbus", "serve"]
    if trace is not None:  # the same serve, its step's phases timed from outside the cycle (serve_phases.py)
        serve = [sys.executable, str(Path(__file__).with_name("serve_phases.py")), str(trace)]
    cmd = [*serve, str(net), *(["--backend", backend] if backend else []), "--domain", str(domain)]
    cmd += ["--interface", "lo", "--json", "--hold-after", "5000", "--stop-after", "10000"]
    cmd += ["--rt-priority", str(priority), "--spin-us", str(spin_us), *extra]
    server = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    watcher = None
    if witness is not None:  # beside serve, at its priority: the machine's own wake-ups, timed
        wcmd = [sys.executable, str(Path(__file__).with_name("wake_witness.py")), str(witness)]
        wcmd += ["--seconds", str(seconds + 60), "--rt-priority", str(witness_priority or priority)]
        wcmd += ["--cpu", str(witness_cpu)] if witness_cpu is not None else []
        watcher = subprocess.Popen(wcmd)
    refused = ""
    try:
        assert server.stdout is not None
        ready = json.loads(server.stdout.readline())
        with fieldbus.remote.connect("bench", domain=domain, interface="lo", client_id="bench") as op:
            op.claim("joints")
            try:
                op.enable("joints")
            except fieldbus.remote.RemoteError as exc:  # e.g. the bus latched its safe stop: say so, go on
                refused = str(exc)
            cpu0, t0, n = _cpu_s(server.pid), time.monotonic(), 0
            while time.monotonic() - t0 < seconds:
                op.exchange(deadline_s=0.05)
                n += 1
            cpu = (_cpu_s(server.pid) - cpu0) / (time.monotonic() - t0)
            misses = op.misses
    finally:
        server.send_signal(signal.SIGTERM)
        out, _ = server.communicate(timeout=60)
        if watcher is not None:
            watcher.send_signal(signal.SIGTERM)
            watcher.wait(timeout=30)
    report = json.loads(out.strip().splitlines()[-1])
    seen = _witnessed(report["stalls"].get("over_5ms_at", []), witness) if witness is not None else None
    phases = json.loads(trace.read_text()) if trace is not None and trace.exists() else None
    return {
        **({"phases": phases} if phases is not None else {}),
        "spin_us": spin_us,
        "realtime": ready["realtime"],
        **({"enable_refused": refused} if refused else {}),
        "client_exchanges": n,
        "client_late": misses,
        "serve_cpu_percent": round(100 * cpu, 1),
        "longest_step_us": report["cycle_time_us"]["max"],
        "step_p99_us": report["cycle_time_us"]["p99"],
        "overruns": report["overruns"],
        "longest_gap_us": report["stalls"]["longest_gap_us"],
        "gaps_over_5ms": report["stalls"]["over_5ms"],
        "stalls_20ms": report["stalls"]["count"],
        "other_threads": [a for a in ready["realtime"]["applied"] if "other thread" in a],
        "bus": report["buses"][0]["type"],
        "bus_misses": report["missed"],
        "bus_timeouts": report["buses"][0]["timeouts"],
        "bus_short": report["buses"][0]["short"],
        "safe_stops": report["safe_stops"],
        "cycles": report["cycles"],
        **({"witness": seen} if seen is not None else {}),
    }


def _witnessed(gaps: list[list[int]], witness: Path) -> dict[str, Any]:
    """The witness's figures and, for each of serve's gaps over 5 ms, the witness's worst round during it
    (how late it woke plus how much longer its work took than usual, us; 0: under 1 ms throughout); a
    gap is witnessed when that reached 1 ms."""
    w = json.loads(witness.read_text())
    late = [(d, d + us * 1000, us) for d, us in w["late"]]  # [deadline, done] ns, excess us
    slow = [(woke, woke + us * 1000, us) for woke, us in w.get("slow", [])]  # its work 5x its median
    rows = []
    for cycle, gap_us, at in gaps:
        worst = max((us for d, end, us in late if d < at and end > at - gap_us * 1000), default=0)
        slowest = max((us for b, end, us in slow if b < at and end > at - gap_us * 1000), default=0)
        rows.append([cycle, gap_us, worst, slowest])
    return {
        "late_max_us": w["late_max_us"],
        "late_p99_us": w["late_p99_us"],
        "work_median_us": w["work_median_us"],
        "work_max_us": w["work_max_us"],
        "rounds_1ms_late": len(late),
        "slow_rounds": len(slow),
        # [cycle, gap us, the witness's worst round in it (late + slow, us), its slowest work in it (us)]
        "gaps_over_5ms": rows,
        "gaps_over_5ms_witnessed": sum(1 for r in rows if r[2] >= 1000 or r[3] > 0),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--rt-priority", type=int, default=50)
    ap.add_argument("--burners", type=int, default=2)
    ap.add_argument("--spin-us", type=int, nargs="+", default=[30, 150])
    ap.add_argument(
        "--veth",
        action="store_true",
        help="serve a real EtherCAT bus: pysoem over a veth pair to the emulator in its own process",
    )
    ap.add_argument("--cpu", type=int, help="serve's --cpu: pin the cycle thread to this CPU")
    ap.add_argument("--lock-memory", action="store_true", help="serve's --lock-memory")
    ap.add_argument("--receive-timeout-us", type=int, default=500, help="the network's receive_timeout_us")
    ap.add_argument(
        "--meter",
        action="store_true",
        help="first, beside the same burners: benchmarks/cpu_meter.py for --seconds at --rt-priority",
    )
    ap.add_argument(
        "--trace", action="store_true", help="time the served step's phases (benchmarks/serve_phases.py)"
    )
    ap.add_argument(
        "--witness",
        action="store_true",
        help="beside serve, benchmarks/wake_witness.py at the same priority: which gaps over 5 ms the "
        "machine also imposed on a thread with no fieldbus in it",
    )
    ap.add_argument("--witness-cpu", type=int, help="the witness on this CPU only (with --cpu: serve's)")
    ap.add_argument(
        "--witness-priority",
        type=int,
        help="the witness's SCHED_FIFO priority (default serve's; above it on serve's CPU, it preempts the "
        "cycle for its 20-60 us and is itself held by nothing but the machine)",
    )
    args = ap.parse_args()
    with contextlib.ExitStack() as stack:
        iface = "sim"
        if args.veth:  # the emulator in its own process (SCHED_FIFO 40 where allowed) on a veth pair
            from sim_slaves.ethercat.veth import emulated_segment

            iface = stack.enter_context(emulated_segment([DEMO_JOINT], count=3)).iface
        return _bench(args, iface)


def _bench(args: argparse.Namespace, iface: str) -> int:
    burners = [subprocess.Popen([sys.executable, "-c", "while 1: pass"]) for _ in range(args.burners)]
    try:
        with tempfile.TemporaryDirectory() as tmp:
            net = Path(tmp) / "bench.yaml"
            net.write_text(
                f"name: bench\ncycle_time_us: 1000\nreceive_timeout_us: {args.receive_timeout_us}\nbuses:\n"
                "  - name: joints\n"
                f"    type: ethercat\n    interface: {iface}\n"
                f"    slaves: [{{name: 'j{{i}}', map: {json.dumps(str(DEMO_JOINT))}, count: 3}}]\n"
            )
            load = os.getloadavg()
            rt = Path("/proc/sys/kernel/sched_rt_runtime_us").read_text().strip()
            print(
                json.dumps({"loadavg": load, "cpus": os.cpu_count(), "sched_rt_runtime_us": rt}), flush=True
            )
            if args.meter:  # the machine's own steadiness, in the same load, just before serve
                meter = [sys.executable, str(Path(__file__).with_name("cpu_meter.py"))]
                meter += ["--seconds", str(args.seconds), "--rt-priority", str(args.rt_priority)]
                out = subprocess.run(meter, capture_output=True, text=True, check=True).stdout
                print(json.dumps({"cpu_meter": json.loads(out)}), flush=True)
            for i, spin in enumerate(args.spin_us):
                domain = 1 + (os.getpid() * 3 + i) % 200
                trace = Path(tmp) / f"phases-{i}.json" if args.trace else None
                backend = None if args.veth else "sim"
                extra = (*(["--cpu", str(args.cpu)] if args.cpu is not None else []),)
                extra += ("--lock-memory",) if args.lock_memory else ()
                seen = Path(tmp) / f"witness-{i}.json" if args.witness else None
                res = _run(
                    net,
                    domain,
                    args.seconds,
                    args.rt_priority,
                    spin,
                    trace,
                    backend,
                    extra,
                    seen,
                    args.witness_cpu,
                    args.witness_priority,
                )
                print(json.dumps(res), flush=True)
            print(json.dumps({"loadavg_after": os.getloadavg()}), flush=True)
    finally:
        for b in burners:
            b.kill()
            b.wait()
    return 0


if __name__ == "__main__":
    sys.exit(main())
