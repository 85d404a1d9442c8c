"""An emulated EtherCAT segment on a veth pair: the wire runner in a child process.

``emulated_segment(maps, count=N)`` creates a uniquely named veth pair, brings
both ends up (IPv6 and ARP off: no stray frames on the segment), starts
``python -m sim_slaves.ethercat`` on the slave end, waits for its ready line
and yields an :class:`Emulator` whose ``iface`` is the master's end. On exit
the runner is terminated and the pair deleted, also after an error.

Needs root (CAP_NET_ADMIN for the pair, CAP_NET_RAW for the sockets);
:class:`VethUnavailable` says precisely why when the machine refuses.
"""

from __future__ import annotations

import itertools
import os
import select
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from fieldbus.errors import FieldbusError

REPO = Path(__file__).resolve().parents[2]
READY_TIMEOUT_S = 30.0
_seq = itertools.count()


class VethUnavailable(FieldbusError):
    """This machine refuses a veth pair or raw sockets (the message says why)."""


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
        """Terminate the runner (SIGTERM, then SIGKILL after 5 s)."""
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)


def _ip(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["ip", *args], capture_output=True, text=True, check=False)


def make_veth_pair() -> tuple[str, str]:
    """Create and bring up a uniquely named veth pair; returns (master end, slave end)."""
    if os.geteuid() != 0:
        raise VethUnavailable(
            "needs root: creating a veth pair and raw AF_PACKET sockets require CAP_NET_ADMIN/CAP_NET_RAW"
        )
    if shutil.which("ip") is None:
        raise VethUnavailable("the 'ip' command (iproute2) is not installed")
    tag = f"{os.getpid() % 1000}{next(_seq)}"
    master, slave = f"fbm{tag}", f"fbs{tag}"
    _ip("link", "del", master)  # leftovers of a killed run
    res = _ip("link", "add", master, "type", "veth", "peer", "name", slave)
    if res.returncode != 0:
        raise VethUnavailable(
            f"'ip link add {master} type veth peer name {slave}' refused: {res.stderr.strip()}"
        )
    for name in (master, slave):
        subprocess.run(
            ["sysctl", "-q", "-w", f"net.ipv6.conf.{name}.disable_ipv6=1"], capture_output=True, check=False
        )
        _ip("link", "set", name, "arp", "off")
        res = _ip("link", "set", name, "up")
        if res.returncode != 0:
            _ip("link", "del", master)
            raise VethUnavailable(f"ip link set {name} up failed: {res.stderr.strip()}")
    return master, slave


def delete_link(name: str) -> None:
    """Delete a link (and with a veth end, its peer). Quiet when it is gone already."""
    _ip("link", "del", name)


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
    raise FieldbusError(f"emulator not ready after {timeout_s} s (exit {proc.poll()}): {err}")


def start_runner(
    iface: str,
    maps: Sequence[Path | str],
    *,
    count: int = 1,
    control: Path,
    pcap: Path | None = None,
    app: str = "auto",
) -> subprocess.Popen[str]:
    """Start ``python -m sim_slaves.ethercat`` on ``iface`` and wait until it is ready."""
    cmd = [sys.executable, "-m", "sim_slaves.ethercat", "--iface", iface, "--count", str(count)]
    cmd += ["--control", str(control), "--app", app]
    for m in maps:
        cmd += ["--map", str(m)]
    if pcap is not None:
        cmd += ["--pcap", str(pcap)]
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")])),
    }
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        _wait_ready(proc, READY_TIMEOUT_S)
    except BaseException:
        proc.kill()
        proc.wait(5)
        raise
    return proc


@contextmanager
def emulated_segment(
    maps: Sequence[Path | str],
    *,
    count: int = 1,
    pcap: Path | None = None,
    app: str = "auto",
    workdir: Path | None = None,
) -> Iterator[Emulator]:
    """A veth pair with the emulator on one end; yields the :class:`Emulator` (``iface`` = master end)."""
    master, slave = make_veth_pair()
    try:
        with tempfile.TemporaryDirectory(prefix="fieldbus-emu-") as tmp:
            control = Path(workdir or tmp) / f"ctl-{slave}.sock"
            proc = start_runner(slave, maps, count=count, control=control, pcap=pcap, app=app)
            emu = Emulator(master, slave, proc, control, pcap)
            try:
                yield emu
            finally:
                emu.stop()
    finally:
        delete_link(master)
