"""An emulated EtherCAT segment on a veth pair: the wire runner in a child process.

``emulated_segment(maps, count=N)`` creates a uniquely named veth pair, brings
both ends up (IPv6 and ARP off: no stray frames on the segment), starts
``python -m sim_slaves.ethercat`` on the slave end, waits for its ready line
and yields an :class:`Emulator` whose ``iface`` is the master's end. On exit
the runner is terminated and the pair deleted, also after an error.

Needs root (CAP_NET_ADMIN for the pair, CAP_NET_RAW for the sockets);
:class:`VethUnavailable` says precisely why when the machine refuses.

Names and ownership: a pair is ``fbm<6 hex>``/``fbs<6 hex>`` from a random
token; creation never deletes an existing link first (a name that exists is
someone's live pair: another token is drawn). The master end carries the
alias ``fieldbus-veth:<pid>`` of the process that made it; a pair is deleted
only by that process, or, left behind by a process that died (killed test
run), by the next :func:`make_veth_pair`, which removes pairs whose owner pid
no longer exists.

The runner's stderr goes to a file, never a pipe nobody reads (a chatty
emulator would block once 64 KiB were buffered); a runner that fails to start
has that file's tail in the error.
"""

from __future__ import annotations

import os
import secrets
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
ALIAS_PREFIX = "fieldbus-veth:"
NAME_TRIES = 20
STDERR_TAIL = 4000  # characters of the runner's stderr quoted when it fails to start


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
    stderr: Path | None = None  # the runner's stderr, as a file

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
    remove_orphaned_pairs()
    for _ in range(NAME_TRIES):
        tag = secrets.token_hex(3)
        master, slave = f"fbm{tag}", f"fbs{tag}"
        res = _ip("link", "add", master, "type", "veth", "peer", "name", slave)
        if res.returncode == 0:
            break
        if "exists" not in res.stderr:
            raise VethUnavailable(
                f"'ip link add {master} type veth peer name {slave}' refused: {res.stderr.strip()}"
            )
    else:
        raise VethUnavailable(f"no free veth name after {NAME_TRIES} tries")
    _ip("link", "set", master, "alias", f"{ALIAS_PREFIX}{os.getpid()}")
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


def owner_pid(name: str) -> int | None:
    """The pid in a link's ``fieldbus-veth:<pid>`` alias, None when it has none (not one of ours)."""
    res = _ip("-o", "link", "show", "dev", name)
    for word_alias in res.stdout.split(" alias ")[1:]:
        alias = word_alias.split()[0] if word_alias.split() else ""
        if alias.startswith(ALIAS_PREFIX) and alias[len(ALIAS_PREFIX) :].isdigit():
            return int(alias[len(ALIAS_PREFIX) :])
    return None


def remove_orphaned_pairs() -> list[str]:
    """Delete our veth pairs whose owner process is gone; returns their master ends. Live pairs stay."""
    res = _ip("-o", "link", "show")
    removed = []
    for line in res.stdout.splitlines():
        parts = line.split(":", 2)
        if len(parts) < 3:
            continue
        name = parts[1].strip().split("@")[0]
        if not name.startswith("fbm"):
            continue
        pid = owner_pid(name)
        if pid is not None and not Path(f"/proc/{pid}").exists():
            delete_link(name)
            removed.append(name)
    return removed


def _tail(path: Path | None) -> str:
    if path is None or not path.exists():
        return ""
    return path.read_text(errors="replace")[-STDERR_TAIL:]


def _wait_ready(proc: subprocess.Popen[str], timeout_s: float, stderr: Path | None = None) -> str:
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
    raise FieldbusError(f"emulator not ready after {timeout_s} s (exit {proc.poll()}): {_tail(stderr)}")


def start_runner(
    iface: str,
    maps: Sequence[Path | str],
    *,
    count: int = 1,
    control: Path,
    pcap: Path | None = None,
    app: str = "auto",
    stderr: Path | None = None,
    command: Sequence[str] | None = None,
) -> subprocess.Popen[str]:
    """Start ``python -m sim_slaves.ethercat`` on ``iface`` and wait until it is ready.

    Its stderr goes to the file ``stderr`` (default: ``runner-<iface>.err`` beside ``control``).
    ``command`` replaces the runner's command line (tests of this function).
    """
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
    if command is not None:
        cmd = list(command)
    err_path = stderr if stderr is not None else control.parent / f"runner-{iface}.err"
    with err_path.open("w") as err:
        proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=err, text=True, env=env)
    try:
        _wait_ready(proc, READY_TIMEOUT_S, err_path)
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
            err = control.parent / f"runner-{slave}.err"
            proc = start_runner(slave, maps, count=count, control=control, pcap=pcap, app=app, stderr=err)
            emu = Emulator(master, slave, proc, control, pcap, err)
            try:
                yield emu
            finally:
                emu.stop()
    finally:
        delete_link(master)
