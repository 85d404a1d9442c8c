"""``fieldbus serve`` with a per-phase timestamp trace of its served step, for ``serve_rt.py --trace``.

    python benchmarks/serve_phases.py OUT.json <fieldbus serve arguments...>

Runs ``fieldbus serve`` in this process after wrapping, at class level, the calls its step makes (the
trace lives here, not in the cycle): ``BusServer.step`` (the whole step), ``StallWatch.tick``, the
request reader's ``take`` (requests), ``ServedGroup.take_commands`` and ``before_exchange`` (commands),
``Operational.exchange``, ``ServedGroup.publish`` and ``BusServer.diagnostics`` plus every DDS writer's
``write`` (publish). Each wrapper adds ``perf_counter_ns`` start/end pairs into preallocated arrays (no
allocation per call); at exit the ``--top`` longest steps are written to OUT.json with the time each phase
took inside them and what is left ("other": the step's own code, or time the thread was not running),
its start (``start_ns``, CLOCK_MONOTONIC: to line it up with ``perf record -k CLOCK_MONOTONIC``) and the
(gap since the previous start, length) of the steps around it (``around_us``),
plus the thread's involuntary context switches over the run (``/proc/thread-self/status``).
"""

from __future__ import annotations

import atexit
import json
import resource
import sys
import time
from collections.abc import Callable
from typing import Any

import numpy as np

PHASES = (
    "step",
    "stall_tick",
    "requests",
    "answer",
    "services",
    "pending",
    "owners",
    "commands",
    "exchange",
    "publish",
    "diagnostics",
    "write",
)
CAP = 2_000_000  # calls kept per phase (a 20 s run at 1 kHz makes at most a few per cycle)
TOP = 10
STARTUP = 300  # steps looked at one by one from the start


class Trace:
    def __init__(self) -> None:
        self.t = {p: np.zeros((CAP, 2), dtype=np.int64) for p in PHASES}
        self.n = dict.fromkeys(PHASES, 0)
        self.depth = dict.fromkeys(PHASES, 0)
        # per step: the thread's CPU time (CLOCK_THREAD_CPUTIME_ID) and its involuntary switches
        self.cpu = np.zeros(CAP, dtype=np.int64)
        self.preempted = np.zeros(CAP, dtype=np.int64)
        self.faults = np.zeros(CAP, dtype=np.int64)  # minor page faults of the thread during the step
        self.sys_us = np.zeros(CAP, dtype=np.int64)  # its kernel time (tick-grained)

    def wrap_step(self, fn: Callable[..., Any]) -> Callable[..., Any]:
        """The step, also with the thread's CPU time and involuntary context switches during it."""
        inner = self.wrap("step", fn)
        cpu, usage, who = time.thread_time_ns, resource.getrusage, resource.RUSAGE_THREAD

        def step(*a: Any, **kw: Any) -> Any:
            i = self.n["step"]
            u0 = usage(who)
            c0 = cpu()
            try:
                return inner(*a, **kw)
            finally:
                c1 = cpu()
                if i < CAP:
                    u1 = usage(who)
                    self.cpu[i], self.preempted[i] = c1 - c0, u1.ru_nivcsw - u0.ru_nivcsw
                    self.faults[i] = u1.ru_minflt - u0.ru_minflt + u1.ru_majflt - u0.ru_majflt
                    self.sys_us[i] = round((u1.ru_stime - u0.ru_stime) * 1e6)

        return step

    def wrap(self, phase: str, fn: Callable[..., Any]) -> Callable[..., Any]:
        arr, clock = self.t[phase], time.perf_counter_ns

        def traced(*a: Any, **kw: Any) -> Any:
            if self.depth[phase]:  # a nested call of the same phase counts once
                return fn(*a, **kw)
            self.depth[phase] += 1
            t0 = clock()
            try:
                return fn(*a, **kw)
            finally:
                i = self.n[phase]
                if i < CAP:
                    arr[i, 0], arr[i, 1] = t0, clock()
                    self.n[phase] = i + 1
                self.depth[phase] -= 1

        return traced

    def report(self, top: int = TOP) -> dict[str, Any]:
        steps = self.t["step"][: self.n["step"]]
        if not len(steps):
            return {"steps": 0}
        dur = steps[:, 1] - steps[:, 0]
        order = np.argsort(dur)[::-1][:top]
        out = [self._row(int(i), steps, dur) for i in order]
        # the start: the steps over 1 ms among the first STARTUP (the claim, the enable, first writes)
        early = [self._row(i, steps, dur) for i in range(min(STARTUP, len(steps))) if dur[i] > 1_000_000]
        # and the gaps over 2 ms between step starts there: (step index, gap µs, the step before it: µs)
        starts = steps[: min(STARTUP, len(steps)), 0]
        gaps = np.diff(starts)
        early_gaps = [
            (int(i) + 1, round(int(gaps[i]) / 1e3), round(int(dur[i]) / 1e3))
            for i in np.flatnonzero(gaps > 2_000_000)
        ]
        q = np.percentile(dur, [50, 99, 99.9]) / 1e3
        n = len(steps)
        return {
            "steps": n,
            "page_faults_per_step_median": float(np.median(self.faults[:n])),
            "phase_median_us": {
                p: round(float(np.median(self.t[p][: self.n[p], 1] - self.t[p][: self.n[p], 0])) / 1e3, 1)
                for p in PHASES
                if self.n[p]
            },
            "step_p50_us": round(float(q[0]), 1),
            "step_p99_us": round(float(q[1]), 1),
            "step_p999_us": round(float(q[2]), 1),
            "longest": out,
            "startup_over_1ms": early,
            "startup_gaps_over_2ms": early_gaps,
        }

    def _row(self, i: int, steps: Any, dur: Any) -> dict[str, Any]:
        """Step ``i``: its length, CPU time, faults and the time each phase took inside it (µs)."""
        a, b = steps[i]
        row: dict[str, Any] = {
            "step_us": round((b - a) / 1e3, 1),
            "thread_cpu_us": round(int(self.cpu[i]) / 1e3, 1),
            "preempted": int(self.preempted[i]),
            "page_faults": int(self.faults[i]),
            "kernel_us": int(self.sys_us[i]),
            "index": int(i),
            "start_ns": int(a),
        }
        inside = 0
        for p in PHASES[1:]:
            t = self.t[p][: self.n[p]]
            sel = (t[:, 0] >= a) & (t[:, 1] <= b)
            spent = int((t[sel, 1] - t[sel, 0]).sum())
            if p == "write":  # writes inside publish/diagnostics are already counted there
                row["of_which_dds_write_us"] = round(spent / 1e3, 1)
                continue
            row[f"{p}_us"] = round(spent / 1e3, 1)
            inside += spent
        row["other_us"] = round((b - a - inside) / 1e3, 1)
        lo, hi = max(0, int(i) - 6), min(len(steps), int(i) + 4)  # the steps around it: start gap, length
        row["around_us"] = [
            (round(int(steps[j, 0] - steps[j - 1, 0]) / 1e3) if j else 0, round(int(dur[j]) / 1e3))
            for j in range(lo, hi)
        ]
        return row


def _switches() -> dict[str, int]:
    out = {}
    try:
        with open("/proc/thread-self/status") as f:
            for line in f:
                if "ctxt_switches" in line:
                    k, v = line.split(":")
                    out[k.strip()] = int(v)
    except OSError:
        pass
    return out


def _steal() -> tuple[int, int] | None:
    """(steal, total) jiffies of all CPUs from /proc/stat, or None."""
    try:
        with open("/proc/stat") as f:
            cols = [int(v) for v in f.readline().split()[1:]]
    except (OSError, ValueError):
        return None
    return (cols[7], sum(cols[:8])) if len(cols) >= 8 else None


def main() -> int:
    path, argv = sys.argv[1], sys.argv[2:]
    from cyclonedds.pub import DataWriter

    from fieldbus.cli import main as cli
    from fieldbus.dds import server
    from fieldbus.dds.service_host import ServiceHost
    from fieldbus.dds.stalls import StallWatch
    from fieldbus.network import Operational

    tr = Trace()
    server.BusServer.step = tr.wrap_step(server.BusServer.step)  # type: ignore[method-assign]
    StallWatch.tick = tr.wrap("stall_tick", StallWatch.tick)  # type: ignore[method-assign]
    server.BusServer._answer = tr.wrap("answer", server.BusServer._answer)  # type: ignore[method-assign]
    server.BusServer._advance_pending = tr.wrap("pending", server.BusServer._advance_pending)  # type: ignore[method-assign]
    server.BusServer._watch_owners = tr.wrap("owners", server.BusServer._watch_owners)  # type: ignore[method-assign]
    ServiceHost.poll = tr.wrap("services", ServiceHost.poll)  # type: ignore[method-assign]
    server.ServedGroup.take_commands = tr.wrap("commands", server.ServedGroup.take_commands)  # type: ignore[method-assign]
    server.ServedGroup.before_exchange = tr.wrap("commands", server.ServedGroup.before_exchange)  # type: ignore[method-assign]
    Operational.exchange = tr.wrap("exchange", Operational.exchange)  # type: ignore[method-assign]
    server.ServedGroup.publish = tr.wrap("publish", server.ServedGroup.publish)  # type: ignore[method-assign]
    server.BusServer.diagnostics = tr.wrap("diagnostics", server.BusServer.diagnostics)  # type: ignore[method-assign]
    DataWriter.write = tr.wrap("write", DataWriter.write)  # type: ignore[method-assign]
    real_init = server.BusServer.__init__

    def init(self: Any, *a: Any, **kw: Any) -> None:
        real_init(self, *a, **kw)
        self.req_reader.take = tr.wrap("requests", self.req_reader.take)

    server.BusServer.__init__ = init  # type: ignore[method-assign]
    before, steal0 = _switches(), _steal()
    interval = float(__import__("os").environ.get("SERVE_SWITCH_INTERVAL_S", "0") or 0)
    if interval > 0:  # the GIL's hand-over interval (default 5 ms): a trial, not serve's setting
        sys.setswitchinterval(interval)

    def dump() -> None:
        import threading

        rep = tr.report()
        rep["python_threads"] = [t.name for t in threading.enumerate()]
        rep["switch_interval_s"] = sys.getswitchinterval()
        after = _switches()
        rep["main_thread_switches"] = {k: after.get(k, 0) - before.get(k, 0) for k in after}
        steal1 = _steal()
        if steal0 and steal1:  # the hypervisor's stolen time, all CPUs: a share of the run's CPU time
            rep["steal_percent"] = round(100 * (steal1[0] - steal0[0]) / max(1, steal1[1] - steal0[1]), 1)
        with open(path, "w") as f:
            json.dump(rep, f)

    atexit.register(dump)
    return cli(["serve", *argv])


if __name__ == "__main__":
    sys.exit(main())
