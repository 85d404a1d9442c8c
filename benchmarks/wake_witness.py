"""A witness of the machine: how late does it wake a SCHED_FIFO thread, and how slowly does it run it?

    python benchmarks/wake_witness.py OUT.json [--seconds 10] [--rt-priority 50] [--late-us 1000] [--chunk 10]

One thread at SCHED_FIFO ``--rt-priority`` sleeps to every millisecond's
deadline (``clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME)``, as the served
cycle does), notes how late it woke (as ``cyclictest`` does), then does a small
fixed piece of work (``--chunk`` sums of a 3-element array, as
``cpu_meter.py``; about 20 µs here) and notes how long it took. A round whose
lateness plus the work's time beyond its median reaches ``--late-us`` is kept
with its deadline (CLOCK_MONOTONIC ns, the served cycle's clock), so that
``serve_rt.py --witness`` can tell whether a gap in the served cycle fell in a
time when the machine also paused or slowed a thread with no fieldbus in it.
Ends after ``--seconds`` or on SIGTERM; writes one JSON object to OUT.json:
rounds, the lateness median / p99 / longest (µs), the work's median and
longest (µs), the kept rounds ``[[deadline_ns, excess_us], ...]`` and the
rounds whose work took 5 times its median or more ``[[woke_ns, work_us], ...]``.
``--cpu``: the witness on that CPU only (beside a served cycle pinned there:
that CPU's own slow spells).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import time
from pathlib import Path

import numpy as np

from fieldbus.platform.clock import DeadlineClock

PERIOD_NS = 1_000_000


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--rt-priority", type=int, default=50)
    ap.add_argument("--late-us", type=int, default=1000, help="keep rounds at least this late (µs)")
    ap.add_argument("--chunk", type=int, default=10, help="array sums of work per round (as cpu_meter.py)")
    ap.add_argument(
        "--cpu", type=int, help="run on this CPU only (the served cycle's, to see its CPU's spells)"
    )
    args = ap.parse_args()
    stop = [False]
    signal.signal(signal.SIGTERM, lambda *_: stop.__setitem__(0, True))
    if args.cpu is not None:
        os.sched_setaffinity(0, {args.cpu})
    if args.rt_priority > 0:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(args.rt_priority))
    clock = DeadlineClock(spin_ns=0)
    a = np.ones(3)
    late: list[tuple[int, int]] = []
    slow: list[tuple[int, int]] = []  # rounds whose work took 5 times its median or more: (deadline, work us)
    lateness: list[int] = []
    work: list[int] = []
    typical = 0  # the work's running median estimate, ns
    deadline = time.monotonic_ns() + PERIOD_NS
    end = deadline + int(args.seconds * 1e9)
    while deadline < end and not stop[0]:
        clock.sleep_until_ns(deadline)
        woke = time.monotonic_ns()
        x = 0.0
        for i in range(args.chunk):
            x += float((a * i).sum())
        done = time.monotonic_ns()
        lateness.append(woke - deadline)
        work.append(done - woke)
        if len(work) == 200 or (len(work) > 200 and len(work) % 1000 == 0):
            typical = sorted(work)[len(work) // 2]
        excess = (woke - deadline) + max(0, done - woke - typical)
        if typical and excess >= args.late_us * 1000:
            late.append((deadline, excess // 1000))
        if typical and done - woke >= 5 * typical:
            slow.append((woke, (done - woke) // 1000))
        deadline += PERIOD_NS
        if done > deadline:  # more than a period late: the next deadline a period from now
            deadline = done + PERIOD_NS
    lateness.sort()
    work.sort()
    n = len(lateness)
    report = {
        "rounds": n,
        "late_median_us": lateness[n // 2] // 1000 if n else 0,
        "late_p99_us": lateness[int(n * 0.99)] // 1000 if n else 0,
        "late_max_us": lateness[-1] // 1000 if n else 0,
        "work_median_us": work[n // 2] // 1000 if n else 0,
        "work_max_us": work[-1] // 1000 if n else 0,
        "late": [list(x) for x in late],
        "slow": [list(x) for x in slow],
    }
    args.out.write_text(json.dumps(report))
    return 0


if __name__ == "__main__":
    sys.exit(main())
