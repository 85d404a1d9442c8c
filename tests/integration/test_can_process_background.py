"""``python -m sim_slaves.can_process`` started in the background (stdin closed) keeps serving.

It used to stop as soon as its stdin read end-of-file, silently: started with
``&`` from a script, it exited right after ``ready``. Now only SIGTERM/SIGINT
stop it, unless ``--exit-with-stdin`` asks for the old behaviour (which says so).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from fieldbus.commands.demo import DEMO_MAP
from sim_slaves.can_process import udp_bus

can = pytest.importorskip("can")

REPO = Path(__file__).resolve().parents[2]
IDENTITY_REQUEST = bytes([0x40, 0x18, 0x10, 0x01, 0, 0, 0, 0])  # SDO upload 0x1018:1 (vendor id)


def _start(where, *extra: str) -> subprocess.Popen[str]:  # type: ignore[no-untyped-def]
    cmd = [sys.executable, "-m", "sim_slaves.can_process", "--kind", "canopen", "--map", str(DEMO_MAP)]
    cmd += ["--nodes", "1", "--interface", where.interface, "--channel", where.channel]
    cmd += [f"--option={k}={v}" for k, v in where.options] + list(extra)
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.Popen(
        cmd, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env
    )
    assert proc.stdout is not None
    assert proc.stdout.readline().strip() == "ready"
    return proc


def _vendor_id(where) -> int | None:  # type: ignore[no-untyped-def]
    """Ask node 1 for its vendor id; None when nobody answers (the bus is quiet for 2 s)."""
    with can.Bus(interface=where.interface, channel=where.channel, **dict(where.options)) as bus:
        bus.send(can.Message(arbitration_id=0x601, data=IDENTITY_REQUEST, is_extended_id=False))
        for _ in range(20):
            msg = bus.recv(timeout=0.1)
            if msg is not None and msg.arbitration_id == 0x581:
                return int.from_bytes(bytes(msg.data[4:8]), "little")
    return None


def test_started_with_stdin_closed_it_serves_until_sigterm() -> None:
    where = udp_bus(7, "fieldbus_udp")
    proc = _start(where)
    try:
        assert _vendor_id(where) == 0x00000FB1
        assert proc.poll() is None
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(10) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)


def test_exit_with_stdin_stops_when_stdin_closes_and_says_why() -> None:
    proc = _start(udp_bus(8, "fieldbus_udp"), "--exit-with-stdin")
    try:
        assert proc.wait(10) == 0
        assert proc.stderr is not None
        assert "stdin closed" in proc.stderr.read()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)
