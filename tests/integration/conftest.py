"""Integration fixtures: a veth pair with the EtherCAT emulator on one end.

``ethercat_emulator(maps, count=..., pcap=..., app=...)`` creates a uniquely
named veth pair, brings both ends up (IPv6 off, ARP off: no stray frames),
starts ``python -m sim_slaves.ethercat`` on the slave end, waits for its ready
line and returns an :class:`Emulator` whose ``iface`` is the master end.
Everything is torn down afterwards (runner terminated, veth pair deleted),
also when the test fails. Skips only when the machine refuses: not root, or
``ip link add`` fails.
"""

from __future__ import annotations

import itertools
import os
import select
import shutil
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

REPO = Path(__file__).resolve().parents[2]
_seq = itertools.count()


@dataclass
class Emulator:
    """A running emulator: ``iface`` is the master's end of the veth pair."""

    iface: str
    peer: str
    proc: subprocess.Popen[str]
    control: Path
    pcap: Path | None

    def command(self, **msg: Any) -> dict[str, Any]:
        """Send a fault-injection / status command to the runner (see sim_slaves.ethercat.runner)."""
        from sim_slaves.ethercat.runner import send_control

        return send_control(self.control, msg)

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)


def _ip(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["ip", *args], capture_output=True, text=True, check=False)


def _veth_pair() -> tuple[str, str]:
    if os.geteuid() != 0:
        pytest.skip(
            "needs root: creating a veth pair and raw AF_PACKET sockets require CAP_NET_ADMIN/CAP_NET_RAW"
        )
    if shutil.which("ip") is None:
        pytest.skip("the 'ip' command (iproute2) is not installed")
    n = next(_seq)
    tag = f"{os.getpid() % 1000}{n}"
    master, slave = f"fbm{tag}", f"fbs{tag}"
    _ip("link", "del", master)  # leftovers of a killed run
    res = _ip("link", "add", master, "type", "veth", "peer", "name", slave)
    if res.returncode != 0:
        pytest.skip(f"'ip link add {master} type veth peer name {slave}' refused: {res.stderr.strip()}")
    for name in (master, slave):
        subprocess.run(
            ["sysctl", "-q", "-w", f"net.ipv6.conf.{name}.disable_ipv6=1"], capture_output=True, check=False
        )
        _ip("link", "set", name, "arp", "off")
        res = _ip("link", "set", name, "up")
        if res.returncode != 0:
            _ip("link", "del", master)
            raise RuntimeError(f"ip link set {name} up failed: {res.stderr.strip()}")
    return master, slave


def _wait_ready(proc: subprocess.Popen[str], timeout_s: float) -> str:
    assert proc.stdout is not None
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        ready, _, _ = select.select([proc.stdout], [], [], 0.1)
        if ready:
            line = proc.stdout.readline()
            if line.startswith("ready "):
                return line.strip()
            if not line and proc.poll() is not None:
                break
    err = proc.stderr.read() if proc.stderr is not None and proc.poll() is not None else ""
    raise RuntimeError(f"emulator not ready after {timeout_s} s (exit {proc.poll()}): {err}")


@pytest.fixture
def ethercat_emulator(tmp_path: Path) -> Iterator[Callable[..., Emulator]]:
    started: list[Emulator] = []
    pairs: list[str] = []

    def start(
        maps: list[Path | str], *, count: int = 1, pcap: Path | None = None, app: str = "auto"
    ) -> Emulator:
        master, slave = _veth_pair()
        pairs.append(master)
        control = tmp_path / f"ctl-{slave}.sock"
        cmd = [sys.executable, "-m", "sim_slaves.ethercat", "--iface", slave, "--count", str(count)]
        cmd += ["--control", str(control), "--app", app]
        for m in maps:
            cmd += ["--map", str(m)]
        if pcap is not None:
            cmd += ["--pcap", str(pcap)]
        proc = subprocess.Popen(
            cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env={**os.environ}
        )
        emu = Emulator(master, slave, proc, control, pcap)
        started.append(emu)
        _wait_ready(proc, 30.0)
        return emu

    try:
        yield start
    finally:
        for emu in started:
            emu.stop()
        for master in pairs:
            _ip("link", "del", master)
