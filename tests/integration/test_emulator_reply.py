"""The wire runner, driven by the real pysoem master over veth, answers from a clear reply path.

Checked: the runner process runs at SCHED_FIFO exactly where it has CAP_SYS_NICE (read from the
process by the kernel, not from the runner), its garbage collector is off and its start-up objects
frozen, and it counts its own reply times for every process-data frame. How fast it answers is
wall clock: that is ``benchmarks/emulator_reply.py`` and docs/emulator.md ("Reply time"), not a test.
"""

from __future__ import annotations

import os
from typing import Any

import pytest

from fieldbus.commands.demo import DEMO_MAP
from sim_slaves.ethercat.runner import CAP_SYS_NICE, DEFAULT_RT_PRIORITY, has_capability

pysoem = pytest.importorskip("pysoem")

pytestmark = pytest.mark.veth
ROUND_TRIPS = 500


def test_the_runner_answers_at_sched_fifo_with_its_collector_off(ethercat_emulator: Any) -> None:
    emu = ethercat_emulator([DEMO_MAP], count=4)
    fifo = has_capability(CAP_SYS_NICE)
    assert (os.sched_getscheduler(emu.proc.pid) == os.SCHED_FIFO) == fifo
    if fifo:
        assert os.sched_getparam(emu.proc.pid).sched_priority == DEFAULT_RT_PRIORITY
    master = pysoem.Master()
    master.open(emu.iface)
    try:
        assert master.config_init() == 4
        master.config_map()
        master.state = pysoem.OP_STATE
        master.write_state()
        for _ in range(1000):
            master.send_processdata()
            master.receive_processdata(10_000)
            if master.state_check(pysoem.OP_STATE, 1000) == pysoem.OP_STATE:
                break
        assert master.read_state() == pysoem.OP_STATE
        emu.command(cmd="timing", reset=True)
        answered = 0
        for _ in range(ROUND_TRIPS):
            master.send_processdata()
            answered += master.receive_processdata(20_000) == master.expected_wkc
        got = emu.command(cmd="timing")
    finally:
        master.state = pysoem.INIT_STATE
        master.write_state()
        master.close()
    assert got["ok"] and got["sched_fifo"] == fifo
    assert got["gc"] == {"enabled": False, "frozen": got["gc"]["frozen"]} and got["gc"]["frozen"] > 1000
    # every answered frame was timed, from the kernel's receipt to the send of its reply
    assert got["reply_us"]["cycles"] >= answered >= ROUND_TRIPS * 0.9
    assert 0 < got["reply_us"]["pickup"]["p50"] <= got["reply_us"]["p50"]
