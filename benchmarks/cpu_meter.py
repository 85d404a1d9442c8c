"""How steady is this machine's CPU for a SCHED_FIFO Python thread? Fixed work every millisecond, timed.

    python benchmarks/cpu_meter.py [--seconds 10] [--rt-priority 50] [--chunk 60]

One thread at SCHED_FIFO ``--rt-priority`` does the same small piece of Python
and numpy work (``--chunk`` sums of a 3-element array, about 0.15 ms here) at
the start of every millisecond and sleeps to the next: the shape of
``fieldbus serve``'s cycle without fieldbus, DDS or a second thread. Each
chunk's wall time and the thread's own CPU time (``CLOCK_THREAD_CPUTIME_ID``)
are kept. A chunk that takes many times its median while its CPU time equals
its wall time was neither preempted nor waiting: the CPU ran the same code
that much slower (a virtual CPU whose host gives it a fraction of a core
without reporting steal time). ``fieldbus serve``'s step meets the same slow
spells, longer by the ratio of its work to the chunk's. One JSON line: the
chunks' median, p99 and longest (µs), the longest one's CPU time, how many
took 5 times the median or more, and the load average.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from typing import Any

import numpy as np


def measure(seconds: float, priority: int, chunk: int) -> dict[str, Any]:
    """Run the meter in this thread (SCHED_FIFO ``priority`` if > 0); restore the policy after."""
    old = os.sched_getscheduler(0), os.sched_getparam(0)
    if priority > 0:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    a = np.ones(3)
    clock, cpu = time.perf_counter_ns, time.thread_time_ns
    n = int(seconds * 1000)
    wall, used = np.zeros(n, dtype=np.int64), np.zeros(n, dtype=np.int64)
    try:
        deadline = clock()
        for k in range(n):
            w0, c0 = clock(), cpu()
            s = 0.0
            for i in range(chunk):
                s += float((a * i).sum())
            wall[k], used[k] = clock() - w0, cpu() - c0
            deadline += 1_000_000
            rest = deadline - clock()
            if rest > 0:
                time.sleep(rest / 1e9)
            else:
                deadline = clock()
    finally:
        os.sched_setscheduler(0, *old)
    median = float(np.median(wall))
    i = int(wall.argmax())
    return {
        "chunks": n,
        "chunk_median_us": round(median / 1e3, 1),
        "chunk_p99_us": round(float(np.percentile(wall, 99)) / 1e3, 1),
        "chunk_max_us": round(int(wall[i]) / 1e3, 1),
        "cpu_in_longest_us": round(int(used[i]) / 1e3, 1),
        "chunks_5x_median": int((wall >= 5 * median).sum()),
        "loadavg": os.getloadavg(),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--rt-priority", type=int, default=50, help="SCHED_FIFO priority (0: normal)")
    ap.add_argument("--chunk", type=int, default=60, help="array sums per millisecond")
    args = ap.parse_args()
    print(json.dumps(measure(args.seconds, args.rt_priority, args.chunk)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
