"""Reply time of the EtherCAT emulator over veth, as the real pysoem master sees it.

    python -m benchmarks.emulator_reply [--round-trips 20000] [--rate 2000] [--slaves 4] [--rounds 3]
        [--before-src DIR] [--runner-args "..."] [--master-priority N] [--json FILE]

The emulator (``python -m sim_slaves.ethercat``, the demo joint map, CiA 402
drives enabled in CSP and holding position) runs in a child process on one
end of a veth pair; pysoem in this process configures it to OP and then
times round trips: ``send_processdata`` + ``receive_processdata`` (one LRW
frame), paced at ``--rate`` on an absolute schedule (a late round trip does
not shift the next ones). Per run: p50, p99, p99.9, max and the count of round
trips over 1 ms; a round trip without the expected working counter within
10 ms counts as lost. A master kept off the CPU for longer than the slaves'
process-data watchdog (100 ms) sees them leave OP (``left OP``): from then on
every round trip counts as lost. With the runner's ``timing`` command (this
checkout) it also prints the emulator's own reply time: from the kernel's
receipt of the frame to its reply's send, the master's side left out.

``--before-src DIR`` is a second checkout (for example ``git worktree add
--detach /tmp/before HEAD~3``): every round runs its emulator and this
checkout's one, alternately in a shuffled order, so both see the same phases
of a shared machine. The figures are wall-clock and belong to this machine
at this time: report the spread over rounds, not the best round.

``--variant NAME=ARGS`` adds a contender: this checkout's emulator with
other arguments (``--variant "no-rt=--rt-priority off"``).

``--master-priority N`` puts this process (the master) at SCHED_FIFO N while
it measures (needs CAP_SYS_NICE); by default it runs as a plain process, as a
user's test would, so its own wake-up after the reply counts in the figure.
Needs root (veth pair, raw sockets).
"""

from __future__ import annotations

import argparse
import json
import os
import random
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks._common import machine_note, table
from sim_slaves.ethercat.runner import send_control
from sim_slaves.ethercat.veth import delete_link, make_veth_pair

REPO = Path(__file__).resolve().parent.parent
MAP = "fieldbus/data/demo_joint.yaml"  # relative to the checkout under test
LOST_TIMEOUT_US = 10_000
ENABLE = (0x06, 0x07, 0x0F)  # shutdown, switch on, enable operation
ENABLE_CYCLES = 40
CSP = 8


@dataclass
class Run:
    """One run's round trips [µs] summarised."""

    name: str
    p50_us: float
    p99_us: float
    p999_us: float
    max_us: float
    over_1ms: int
    lost: int
    round_trips: int
    late_starts: int  # round trips the master began more than one period late (the master's own lateness)
    emulator: dict[str, Any] | None  # the emulator's own reply times ({"cmd": "timing"}), if it has them
    left_op: int  # slaves not in OP at the end (a process-data watchdog tripped: the master was away)
    runner_cpu: float  # the emulator's CPU time over the round trips' wall time (1.0: one CPU busy)


def _start_runner(
    src: Path, iface: str, slaves: int, extra: list[str], control: Path
) -> subprocess.Popen[str]:
    env = {**os.environ, "PYTHONPATH": str(src)}
    cmd = [sys.executable, "-m", "sim_slaves.ethercat", "--iface", iface, "--map", MAP]
    cmd += ["--count", str(slaves), "--control", str(control)]
    proc = subprocess.Popen(
        [*cmd, *extra], cwd=src, env=env, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True
    )
    assert proc.stdout is not None
    line = proc.stdout.readline()
    if not line.startswith("ready"):
        proc.kill()
        raise RuntimeError(f"emulator from {src} did not start: {line!r}")
    return proc


def _output(controlword: int) -> bytes:
    """The demo joint's outputs: controlword, target position 0, target torque 0, mode CSP."""
    return controlword.to_bytes(2, "little") + bytes(4) + bytes(2) + CSP.to_bytes(1, "little", signed=True)


def _bring_up(m: object, slaves: int) -> None:
    import pysoem

    assert m.config_init() == slaves  # type: ignore[attr-defined]
    m.config_map()  # type: ignore[attr-defined]
    m.state = pysoem.OP_STATE  # type: ignore[attr-defined]
    m.write_state()  # type: ignore[attr-defined]
    for _ in range(1000):
        m.send_processdata()  # type: ignore[attr-defined]
        m.receive_processdata(LOST_TIMEOUT_US)  # type: ignore[attr-defined]
        if m.state_check(pysoem.OP_STATE, 1000) == pysoem.OP_STATE:  # type: ignore[attr-defined]
            break
    else:
        raise RuntimeError("the emulated slaves did not reach OP")
    for cw in ENABLE:
        for s in m.slaves:  # type: ignore[attr-defined]
            s.output = _output(cw)
        for _ in range(ENABLE_CYCLES):
            m.send_processdata()  # type: ignore[attr-defined]
            m.receive_processdata(LOST_TIMEOUT_US)  # type: ignore[attr-defined]
    words = [int.from_bytes(bytes(s.input)[:2], "little") for s in m.slaves]  # type: ignore[attr-defined]
    if any(w & 0x6F != 0x27 for w in words):
        raise RuntimeError(f"not every drive is OPERATION ENABLED: {[hex(w) for w in words]}")


def _sleep_until(t_ns: int) -> None:
    """Sleep to about 100 µs before ``t_ns`` (perf_counter), then spin."""
    clock = time.perf_counter_ns
    left = t_ns - clock()
    if left > 200_000:
        time.sleep((left - 100_000) / 1e9)
    while clock() < t_ns:
        pass


def _cpu_s(pid: int) -> float:
    """User + system CPU time of process ``pid`` so far [s] (/proc/PID/stat fields 14 and 15)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def measure(name: str, src: Path, args: argparse.Namespace) -> Run:
    """One run: an emulator from ``src`` on a fresh veth pair, ``args.round_trips`` timed round trips."""
    import pysoem

    master_if, slave_if = make_veth_pair()
    proc = None
    tmp = tempfile.TemporaryDirectory(prefix="fb-reply-")
    control = Path(tmp.name) / "ctl.sock"
    emulator = None
    left_op = 0
    try:
        proc = _start_runner(src, slave_if, args.slaves, shlex.split(args.runner_args), control)
        m = pysoem.Master()
        m.open(master_if)
        try:
            _bring_up(m, args.slaves)
            send_control(control, {"cmd": "timing", "reset": True})
            cpu0, wall0 = _cpu_s(proc.pid), time.monotonic()
            expected = m.expected_wkc
            n = args.round_trips
            rtt = np.zeros(n, dtype=np.int64)
            period = round(1e9 / args.rate)
            clock = time.perf_counter_ns
            lost = late = 0
            old = os.sched_getscheduler(0), os.sched_getparam(0)
            if args.master_priority:
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(args.master_priority))
            try:
                start = clock() + period
                for k in range(n):
                    due = start + k * period
                    _sleep_until(due)
                    t0 = clock()
                    if t0 - due > period:
                        late += 1
                    m.send_processdata()
                    wkc = m.receive_processdata(LOST_TIMEOUT_US)
                    rtt[k] = clock() - t0
                    if wkc != expected:
                        lost += 1
            finally:
                os.sched_setscheduler(0, *old)
            runner_cpu = (_cpu_s(proc.pid) - cpu0) / (time.monotonic() - wall0)
            answer = send_control(control, {"cmd": "timing"})
            emulator = answer.get("reply_us") if answer.get("ok") else None
            m.read_state()
            left_op = sum(1 for s in m.slaves if s.state != pysoem.OP_STATE)
        finally:
            m.close()
    finally:
        if proc is not None:
            proc.terminate()
            proc.wait(5)
        delete_link(master_if)
        tmp.cleanup()
    us = rtt / 1000.0
    p50, p99, p999 = np.percentile(us, [50, 99, 99.9])
    return Run(
        name,
        float(p50),
        float(p99),
        float(p999),
        float(us.max()),
        int(np.count_nonzero(us > 1000.0)),
        lost,
        n,
        late,
        emulator,
        left_op,
        runner_cpu,
    )


def _span(values: list[float], fmt: str = "{:.0f}") -> str:
    mid = statistics.median(values)
    if len(values) == 1:
        return fmt.format(mid)
    return f"{fmt.format(mid)} ({fmt.format(min(values))}-{fmt.format(max(values))})"


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--round-trips", type=int, default=20_000)
    p.add_argument("--rate", type=float, default=2000.0, help="round trips per second [Hz]")
    p.add_argument("--slaves", type=int, default=4)
    p.add_argument("--rounds", type=int, default=1)
    p.add_argument("--before-src", type=Path, help="a second checkout, timed alternately with this one")
    p.add_argument("--runner-args", default="", help="extra arguments for this checkout's emulator")
    p.add_argument(
        "--variant",
        action="append",
        default=[],
        metavar="NAME=ARGS",
        help="another contender: this checkout's emulator with these extra arguments (repeatable)",
    )
    p.add_argument("--before-args", default="", help="extra arguments for the --before-src emulator")
    p.add_argument(
        "--master-priority", type=int, default=0, help="SCHED_FIFO priority of the master (0: none)"
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the order within a round")
    p.add_argument("--json", type=Path, help="write every run as JSON here")
    args = p.parse_args()
    if os.geteuid() != 0:
        print("needs root: a veth pair and raw sockets", file=sys.stderr)
        return 2
    contenders = {"after": (REPO, args.runner_args)}
    for v in args.variant:
        name, _, extra = v.partition("=")
        contenders[name] = (REPO, extra)
    if args.before_src is not None:
        contenders["before"] = (args.before_src.resolve(), args.before_args)
    rng = random.Random(args.seed)
    runs: dict[str, list[Run]] = {c: [] for c in contenders}
    print(machine_note())
    print(
        f"{args.round_trips} round trips at {args.rate:g} Hz, {args.slaves} slaves, "
        f"master {'SCHED_FIFO ' + str(args.master_priority) if args.master_priority else 'SCHED_OTHER'}"
    )
    for r in range(args.rounds):
        order = list(contenders)
        rng.shuffle(order)
        for name in order:
            src, extra = contenders[name]
            saved, args.runner_args = args.runner_args, extra
            try:
                run = measure(name, src, args)
            finally:
                args.runner_args = saved
            runs[name].append(run)
            print(
                f"round {r + 1} {name:>6}: p50 {run.p50_us:.0f} p99 {run.p99_us:.0f} "
                f"p99.9 {run.p999_us:.0f} max {run.max_us:.0f} us, over 1 ms {run.over_1ms}, "
                f"lost {run.lost}, master late {run.late_starts}, left OP {run.left_op}, "
                f"emulator CPU {100 * run.runner_cpu:.0f}%"
                + (
                    f"; in the emulator p50 {run.emulator['p50']:.0f} p99.9 {run.emulator['p99.9']:.0f} "
                    f"max {run.emulator['max']:.0f} us, over 1 ms {run.emulator['over_1ms']:.0f} "
                    f"(pickup p99.9 {run.emulator['pickup']['p99.9']:.0f} max {run.emulator['pickup']['max']:.0f})"
                    if run.emulator
                    else ""
                ),
                flush=True,
            )
    rows = []
    for name, rs in runs.items():
        rows.append(
            [
                name,
                _span([x.p50_us for x in rs]),
                _span([x.p99_us for x in rs]),
                _span([x.p999_us for x in rs]),
                _span([x.max_us for x in rs]),
                _span([float(x.over_1ms) for x in rs]),
                str(sum(x.lost for x in rs)),
                _span([100 * x.runner_cpu for x in rs]),
            ]
        )
    print()
    print(
        table(["emulator", "p50 [µs]", "p99", "p99.9", "max", "over 1 ms", "lost", "emulator CPU [%]"], rows)
    )
    print("(median of the rounds, range in brackets)")
    if args.json is not None:
        args.json.write_text(json.dumps({c: [asdict(x) for x in rs] for c, rs in runs.items()}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
