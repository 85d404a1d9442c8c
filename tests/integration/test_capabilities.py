"""Capabilities asked of the kernel, not guessed from the user id: root in a container without
CAP_SYS_NICE and CAP_IPC_LOCK (``ulimit -r`` 0) is what ``capsh --drop`` makes here.

The probes of :mod:`fieldbus.platform.capabilities` must say no there and yes where the kernel
allows it, and the real-time tests must then skip with the kernel's reason or pass, never fail.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from fieldbus.platform import capabilities
from fieldbus.platform.rt import RtConfig, realtime

REPO = Path(__file__).resolve().parents[2]
DROP = "cap_sys_nice,cap_ipc_lock"
PROBE = (
    "import json\n"
    "from fieldbus.platform import capabilities as c\n"
    "print(json.dumps([c.missing(c.CAP_SYS_NICE, c.CAP_IPC_LOCK), c.fifo_refused(20), c.memory_lock_refused()]))\n"
)


def _without(command: list[str]) -> subprocess.CompletedProcess[str]:
    """``command`` run by ``capsh --drop=cap_sys_nice,cap_ipc_lock`` with ``ulimit -r`` 0; skips where
    capsh is missing or may not drop them (it needs CAP_SETPCAP)."""
    capsh = shutil.which("capsh")
    if capsh is None:
        pytest.skip("capsh (libcap2-bin) is not installed")
    if capabilities.missing(capabilities.CAP_SYS_NICE, capabilities.CAP_IPC_LOCK):
        pytest.skip("this process holds neither to drop: the plain test run is already that case")
    if capabilities.effective() >> 8 & 1 == 0:  # CAP_SETPCAP
        pytest.skip("dropping capabilities needs CAP_SETPCAP")
    shell = "ulimit -r 0; exec " + " ".join(f"'{a}'" for a in command)
    return subprocess.run(
        [capsh, f"--drop={DROP}", "--", "-c", shell], capture_output=True, text=True, cwd=REPO, check=False
    )


def test_the_probes_follow_the_kernel() -> None:
    res = _without([sys.executable, "-c", PROBE])
    assert res.returncode == 0, res.stderr
    lacking, fifo, lock = json.loads(res.stdout)
    assert lacking == ["CAP_SYS_NICE", "CAP_IPC_LOCK"]
    assert fifo == "SCHED_FIFO priority 20 refused (Operation not permitted)"
    assert lock is not None and lock.startswith("mlockall refused")
    # and here, with both: the probe's yes is what realtime() then does
    if capabilities.fifo_refused(20) is None:
        with realtime(RtConfig(priority=20, strict=True)) as state:
            assert state.applied == ["SCHED_FIFO priority 20"]
        assert os.sched_getscheduler(0) != os.SCHED_FIFO  # restored


@pytest.mark.timeout(300)
def test_real_time_tests_skip_with_the_reason_or_pass_without_cap_sys_nice() -> None:
    tests = [
        "tests/unit/test_realtime.py::test_settings_apply_inside_and_are_restored_after",
        "tests/integration/test_demo.py::test_demo_real_time_flags_latency_histograms_and_plot",
    ]
    res = _without([sys.executable, "-m", "pytest", "-q", "-rs", "-p", "no:cacheprovider", *tests])
    assert res.returncode == 0, res.stdout[-3000:]
    assert "1 passed, 1 skipped" in res.stdout, res.stdout[-3000:]
    assert "SCHED_FIFO priority 20 refused (Operation not permitted)" in res.stdout
