"""Real-time settings (SCHED_FIFO, affinity, mlockall) applied and restored; refusals named; latency histograms."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from fieldbus.platform import capabilities
from fieldbus.platform.allocs import net_blocks
from fieldbus.platform.rt import RtConfig, RtError, realtime
from fieldbus.platform.timing import LatencyHistogram


def test_histogram_percentiles_match_numpy_to_the_microsecond() -> None:
    rng = np.random.default_rng(3)
    ns = (rng.gamma(2.0, 40_000.0, 50_000)).astype(np.int64)  # a long-tailed latency, mean 80 µs
    h = LatencyHistogram(max_us=20_000)
    for v in ns:
        h.add(int(v))
    for q in (50, 99, 99.9):
        assert abs(h.percentile_us(q) - np.percentile(ns, q) / 1000) <= 1.0, q
    assert h.to_json()["max"] == round(ns.max() / 1000, 1)
    h.add(10**9)  # beyond the last bin: counted there, its maximum exact
    assert h.counts[-1] >= 1 and h.to_json()["max"] == 1_000_000.0


def test_adding_to_a_histogram_allocates_nothing() -> None:
    h = LatencyHistogram()
    assert net_blocks(lambda: h.add(123_456), cycles=5_000, warmup=500) == 0


def _rt_allowed(priority: int) -> None:
    """Skip unless this process may set SCHED_FIFO at ``priority`` and lock its memory: decided by
    asking the kernel (a probe), not the user id - root in a container often may not."""
    why = [w for w in (capabilities.fifo_refused(priority), capabilities.memory_lock_refused()) if w]
    if why:
        pytest.skip(f"this machine refuses: {'; '.join(why)}")


def test_settings_apply_inside_and_are_restored_after() -> None:
    _rt_allowed(20)
    before = (os.sched_getscheduler(0), os.sched_getparam(0).sched_priority, os.sched_getaffinity(0))
    cpu = max(os.sched_getaffinity(0))
    with realtime(RtConfig(priority=20, cpu=cpu, lock_memory=True, strict=True)) as state:
        assert os.sched_getscheduler(0) == os.SCHED_FIFO and os.sched_getparam(0).sched_priority == 20
        assert os.sched_getaffinity(0) == {cpu}
        with open("/proc/self/status") as f:
            locked_kb = next(int(line.split()[1]) for line in f if line.startswith("VmLck:"))
        assert locked_kb > 16 * 1024  # the prefaulted heap at least
        assert len(state.applied) == 3 and not state.refused
    assert (os.sched_getscheduler(0), os.sched_getparam(0).sched_priority, os.sched_getaffinity(0)) == before
    with open("/proc/self/status") as f:
        assert next(int(line.split()[1]) for line in f if line.startswith("VmLck:")) == 0


def test_fifo_later_checks_the_priority_at_once_and_gives_it_when_asked() -> None:
    """``fifo_later``: set-up work runs at the thread's own priority until start_fifo(); a second call does
    nothing; the exit restores it; a priority out of range is refused at entry, not later."""
    _rt_allowed(20)
    before = (os.sched_getscheduler(0), os.sched_getparam(0).sched_priority)
    with realtime(RtConfig(priority=20, strict=True), fifo_later=True) as state:
        assert (os.sched_getscheduler(0), os.sched_getparam(0).sched_priority) == before
        assert state.fifo is None and not state.applied
        state.start_fifo()
        assert os.sched_getscheduler(0) == os.SCHED_FIFO and os.sched_getparam(0).sched_priority == 20
        assert state.fifo == 20 and state.applied == ["SCHED_FIFO priority 20"]
        state.start_fifo()
        assert state.applied == ["SCHED_FIFO priority 20"]
    assert (os.sched_getscheduler(0), os.sched_getparam(0).sched_priority) == before
    with (
        pytest.raises(RtError, match=r"outside 1\.\.99"),
        realtime(RtConfig(priority=0, strict=True), fifo_later=True),
    ):
        pass
    with realtime(RtConfig(priority=20), fifo_later=True):
        pass  # never started: nothing to restore
    assert (os.sched_getscheduler(0), os.sched_getparam(0).sched_priority) == before


# the child scripts' threads: start(role) makes one that notes its native id in ids[role] and waits for go
_THREADS = """
import json, os, sys, threading
p = int(sys.argv[1])
go = threading.Event()
ids = {}
def wait(role, up):
    ids[role] = threading.get_native_id()
    up.set()
    go.wait()
def start(role):
    up = threading.Event()
    t = threading.Thread(target=wait, args=(role, up))
    t.start()
    up.wait()  # blocks (no spin: a spinning SCHED_FIFO thread could keep the new one off a single CPU)
    return t
"""


_RAISE_CHILD = (
    _THREADS
    + """
from fieldbus.platform.rt import raise_threads
threads = [start("chosen-1"), start("chosen-2"), start("left")]
os.sched_setscheduler(ids["chosen-2"], os.SCHED_FIFO, os.sched_param(5))  # already real-time: left as it is
line = raise_threads([ids["chosen-1"], ids["chosen-2"]], p)
out = {r: [os.sched_getscheduler(t), os.sched_getparam(t).sched_priority] for r, t in ids.items()}
go.set()
for t in threads:
    t.join()
print(json.dumps({"line": line, "threads": out}))
"""
)


@pytest.mark.parametrize("priority", [19, 0])
def test_raise_threads_gives_the_named_normal_threads_the_priority_and_no_other(priority: int) -> None:
    if why := capabilities.fifo_refused(20):
        pytest.skip(f"this machine refuses: {why}")
    run = subprocess.run(
        [sys.executable, "-c", _RAISE_CHILD, str(priority)], capture_output=True, text=True, timeout=60
    )
    assert run.returncode == 0, run.stderr
    out = json.loads(run.stdout)
    fifo, other = os.SCHED_FIFO, os.SCHED_OTHER
    assert out["threads"] == {
        "chosen-1": [fifo, priority] if priority else [other, 0],
        "chosen-2": [fifo, 5],
        "left": [other, 0],
    }
    if priority:
        assert out["line"] == f"1 other thread(s) below the cycle: SCHED_FIFO priority {priority}"
    else:
        assert "normal priority" in out["line"]


_RANK_CHILD = (
    _THREADS
    + """
from fieldbus.platform.rt import rank_below
threads = [start("normal")]  # made before the switch: SCHED_OTHER
os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(p))
threads += [start("inherited-1"), start("inherited-2"), start("lower")]  # made after it: SCHED_FIFO p
os.sched_setscheduler(ids["lower"], os.SCHED_FIFO, os.sched_param(max(1, p - 5)))
line = rank_below(p)
ids["cycle"] = threading.get_native_id()
out = {r: [os.sched_getscheduler(t), os.sched_getparam(t).sched_priority] for r, t in ids.items()}
go.set()
for t in threads:
    t.join()
print(json.dumps({"line": line, "threads": out}))
"""
)


@pytest.mark.parametrize("priority", [20, 1])
def test_rank_below_puts_every_other_thread_at_the_cycles_priority_one_below_it(priority: int) -> None:
    """Threads started after the switch inherit the cycle's SCHED_FIFO priority; rank_below moves them one
    under it (SCHED_OTHER under priority 1) and leaves the cycle, normal threads and lower ones as they are."""
    if why := capabilities.fifo_refused(20):
        pytest.skip(f"this machine refuses: {why}")
    run = subprocess.run(
        [sys.executable, "-c", _RANK_CHILD, str(priority)], capture_output=True, text=True, timeout=60
    )
    assert run.returncode == 0, run.stderr
    out = json.loads(run.stdout)
    fifo, other = os.SCHED_FIFO, os.SCHED_OTHER
    below = [fifo, priority - 1] if priority > 1 else [other, 0]
    assert out["threads"] == {
        "cycle": [fifo, priority],
        "normal": [other, 0],
        "inherited-1": below,
        "inherited-2": below,
        "lower": [fifo, max(1, priority - 5)] if priority > 1 else below,
    }
    where = f"SCHED_FIFO priority {priority - 1}" if priority > 1 else "SCHED_OTHER"
    moved = 2 if priority > 1 else 3
    assert out["line"] == f"{moved} other thread(s) below the cycle: {where}"


def test_a_cpu_that_does_not_exist_is_named_and_strict_makes_it_an_error() -> None:
    lines: list[str] = []
    with realtime(RtConfig(cpu=4096), warn=lines.append) as state:
        assert os.sched_getaffinity(0) != {4096}
    assert state.refused == [f"CPU 4096 does not exist (this machine has CPUs 0-{(os.cpu_count() or 1) - 1})"]
    assert lines == ["real-time: " + state.refused[0]]
    with pytest.raises(RtError, match="CPU 4096 does not exist"), realtime(RtConfig(cpu=4096, strict=True)):
        pass


def test_without_the_capability_the_line_says_what_is_needed() -> None:
    """An unprivileged process (uid nobody, no rtprio limit) asks for SCHED_FIFO and locked memory."""
    if lacking := capabilities.missing(capabilities.CAP_SETUID, capabilities.CAP_SETGID):
        pytest.skip(f"becoming uid nobody needs {' and '.join(lacking)}")
    code = (
        "import json, os, resource\n"
        "from fieldbus.platform.rt import RtConfig, realtime\n"  # imported first: nobody cannot read root's files
        "resource.setrlimit(resource.RLIMIT_RTPRIO, (0, 0))\n"
        "resource.setrlimit(resource.RLIMIT_MEMLOCK, (65536, 65536))\n"
        "os.setgid(65534); os.setuid(65534)\n"
        "with realtime(RtConfig(priority=30, lock_memory=True)) as s:\n"
        "    print(json.dumps(s.to_json()))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=False, cwd="/")
    assert out.returncode == 0, out.stderr
    refused = json.loads(out.stdout)["refused"]
    assert any(
        "SCHED_FIFO priority 30 refused (EPERM): needs CAP_SYS_NICE" in r and "ulimit -r" in r
        for r in refused
    )
    assert any("mlockall refused" in r and "CAP_IPC_LOCK" in r and "ulimit -l" in r for r in refused), refused
