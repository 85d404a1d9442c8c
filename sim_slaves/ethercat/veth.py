"""An emulated EtherCAT segment on a veth pair: the wire runner in a child process.

``emulated_segment(maps, count=N)`` creates a uniquely named veth pair, brings
both ends up (IPv6 and ARP off: no stray frames on the segment), starts
``python -m sim_slaves.ethercat`` on the slave end, waits for its ready line
and yields an :class:`Emulator` whose ``iface`` is the master's end. On exit
the runner is terminated and the pair deleted, also after an error.

Needs CAP_NET_ADMIN (the pair) and CAP_NET_RAW (the sockets), as root has them outside a container;
:class:`VethUnavailable` says precisely why when the machine refuses.

Names and ownership: a pair is ``fbm<6 hex>``/``fbs<6 hex>`` (9 characters,
IFNAMSIZ allows 15) from a random token, never from the pid: two processes
draw independent names. Creation never deletes an existing link first: ``ip
link add`` refusing with EEXIST means the name is someone's pair (live or
not), and another token is drawn (:data:`NAME_TRIES` times). Right after
creation the master end gets the alias ``fieldbus-veth:<pid>:<start>:<pidns>``
(:func:`owner_alias`): the creating process's pid, its start time (clock ticks
after boot, field 22 of ``/proc/<pid>/stat``) and the inode of its pid
namespace. A process deletes only the pairs it created (``emulated_segment``,
or the caller of :func:`make_veth_pair` with :func:`delete_link`).

The one exception are pairs whose owner is provably dead (a killed test run
cannot clean up): :func:`make_veth_pair` first calls
:func:`remove_orphaned_pairs`, which deletes an ``fbm`` link only when its
alias is ours and, seen from the same pid namespace, either no process has
that pid any more or the process that has it started at another time (the
pid was reused). A pair whose owner lives, lives in another pid namespace
(its pid means nothing here), is unreadable, or that has no such alias (not
ours, or its creator was killed between ``ip link add`` and setting the
alias: a leak, never a wrong delete) is left alone. The alias is read again
just before the delete, so a name freed and drawn again meanwhile is not hit.
Aliases of the earlier ``fieldbus-veth:<pid>`` form count as dead only when
``/proc/<pid>`` is gone.

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
from fieldbus.platform import capabilities

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
    """Create and bring up a uniquely named veth pair owned by this process; returns (master end, slave end).

    Pairs left by dead processes are removed first (:func:`remove_orphaned_pairs`);
    an existing name is never deleted, another one is drawn.
    """
    if lacking := capabilities.missing(capabilities.CAP_NET_ADMIN, capabilities.CAP_NET_RAW):
        raise VethUnavailable(
            f"this process lacks {' and '.join(lacking)}: creating a veth pair needs CAP_NET_ADMIN, "
            "its raw AF_PACKET sockets CAP_NET_RAW (root has both outside a container)"
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
    res = _ip("link", "set", master, "alias", owner_alias())
    if res.returncode != 0:
        _ip("link", "del", master)
        raise VethUnavailable(f"ip link set {master} alias failed: {res.stderr.strip()}")
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


@dataclass(frozen=True)
class Owner:
    """The process that created a pair, from its master end's alias."""

    pid: int
    start: int | None  # clock ticks after boot (/proc/<pid>/stat field 22); None: not recorded
    pidns: int | None  # inode of its pid namespace; None: not recorded


def _start_ticks(pid: int) -> int | None:
    """When process ``pid`` started (clock ticks after boot), None when there is none or it is unreadable."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = stat.rsplit(")", 1)[-1].split()  # after the command name, which may hold spaces and ')'
    return int(fields[19]) if len(fields) > 19 and fields[19].isdigit() else None


def _pid_namespace() -> int | None:
    try:
        return os.stat("/proc/self/ns/pid").st_ino
    except OSError:
        return None


def owner_alias(pid: int | None = None) -> str:
    """The alias that marks a pair as created by ``pid`` (default: this process)."""
    pid = os.getpid() if pid is None else pid
    return f"{ALIAS_PREFIX}{pid}:{_start_ticks(pid) or 0}:{_pid_namespace() or 0}"


def parse_owner(alias: str) -> Owner | None:
    """The :class:`Owner` in an alias of ours (either form), None for any other alias."""
    if not alias.startswith(ALIAS_PREFIX):
        return None
    parts = alias[len(ALIAS_PREFIX) :].split(":")
    if not all(p.isdigit() for p in parts) or len(parts) not in (1, 3):
        return None
    if len(parts) == 1:
        return Owner(int(parts[0]), None, None)
    pid, start, pidns = (int(p) for p in parts)
    return Owner(pid, start or None, pidns or None)


def _aliases(*dev: str) -> dict[str, str]:
    """Link name -> alias of every link (or of ``dev``) that has one."""
    res = _ip("-o", "link", "show", *(("dev", *dev) if dev else ()))
    out = {}
    for line in res.stdout.splitlines():
        parts = line.split(":", 2)
        if len(parts) < 3 or " alias " not in parts[2]:
            continue
        words = parts[2].split(" alias ", 1)[1].split()
        if words:
            out[parts[1].strip().split("@")[0]] = words[0]
    return out


def link_owner(name: str) -> Owner | None:
    """The owner recorded on link ``name``, None when it has no alias of ours."""
    alias = _aliases(name).get(name)
    return parse_owner(alias) if alias is not None else None


def owner_pid(name: str) -> int | None:
    """The pid in a link's ``fieldbus-veth:`` alias, None when it has none (not one of ours)."""
    owner = link_owner(name)
    return owner.pid if owner is not None else None


def owner_is_dead(owner: Owner) -> bool:
    """True only when provably dead: same pid namespace, and the pid is gone or belongs to a later process."""
    if owner.pidns is not None and owner.pidns != _pid_namespace():
        return False  # another pid namespace: its pids say nothing here
    if not Path(f"/proc/{owner.pid}").exists():
        return True
    if owner.start is None:
        return False
    start = _start_ticks(owner.pid)
    return start is not None and start != owner.start


def remove_orphaned_pairs() -> list[str]:
    """Delete our veth pairs whose owner process is provably dead; returns their master ends. Others stay."""
    removed = []
    for name, alias in _aliases().items():
        owner = parse_owner(alias)
        if not name.startswith("fbm") or owner is None or not owner_is_dead(owner):
            continue
        if _aliases(name).get(name) != alias:
            continue  # gone, or deleted and drawn again by a live process meanwhile
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
    network: Path | None = None,
    bus: str | None = None,
) -> subprocess.Popen[str]:
    """Start ``python -m sim_slaves.ethercat`` on ``iface`` and wait until it is ready.

    Its stderr goes to the file ``stderr`` (default: ``runner-<iface>.err`` beside ``control``).
    ``command`` replaces the runner's command line (tests of this function). With ``network``
    the slaves are that file's EtherCAT bus (``bus``: which one), with their ``emulator:`` options
    (``maps`` unused).
    """
    cmd = [sys.executable, "-m", "sim_slaves.ethercat", "--iface", iface]
    cmd += ["--control", str(control), "--app", app]
    if network is not None:
        cmd += ["--network", str(network)]
        if bus is not None:
            cmd += ["--bus", bus]
    else:
        cmd += ["--count", str(count)]
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
        # its own process group: a Ctrl-C at the terminal reaches the master only, which stops the
        # emulated drives over the bus and then this runner (a runner stopped first leaves no one to answer)
        proc = subprocess.Popen(
            cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=err, text=True, env=env, process_group=0
        )
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
    network: Path | None = None,
    bus: str | None = None,
) -> Iterator[Emulator]:
    """A veth pair with the emulator on one end; yields the :class:`Emulator` (``iface`` = master end).

    ``network``: build the slaves from that network file's EtherCAT bus instead of ``maps``
    (with the slaves' ``emulator:`` options; the file's interface name is not used); ``bus``
    names that bus when the file has several.
    """
    master, slave = make_veth_pair()
    try:
        with tempfile.TemporaryDirectory(prefix="fieldbus-emu-") as tmp:
            control = Path(workdir or tmp) / f"ctl-{slave}.sock"
            err = control.parent / f"runner-{slave}.err"
            proc = start_runner(
                slave,
                maps,
                count=count,
                control=control,
                pcap=pcap,
                app=app,
                stderr=err,
                network=network,
                bus=bus,
            )
            emu = Emulator(master, slave, proc, control, pcap, err)
            # import the control channel's module now, not at the first fault injection: that import
            # (50-100 ms) stalled a running master past the slaves' 100 ms process-data watchdog
            import sim_slaves.ethercat.runner  # noqa: F401

            try:
                yield emu
            finally:
                emu.stop()
    finally:
        delete_link(master)
