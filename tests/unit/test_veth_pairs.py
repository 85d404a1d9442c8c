"""veth pairs that never collide, and an emulator whose stderr cannot fill up (sim_slaves.ethercat.veth).

A live pair of another process is never deleted, even when it has the very
name this process is about to create; pairs of provably dead processes are
removed, every other pair stays; a runner that writes megabytes to stderr
keeps answering, and one that fails to start still reports its last words.

The pair tests need root and veth; they skip with the machine's reason
(:class:`~sim_slaves.ethercat.veth.VethUnavailable`) only when it refuses.
The stderr tests with a stand-in runner run anywhere.

(Named ``test_veth_pairs.py``: ``tests/integration/test_veth.py`` exists and
the test directories are not packages, so a second ``test_veth.py`` would
stop pytest collecting either.)
"""

from __future__ import annotations

import os
import secrets
import socket
import struct
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from fieldbus.errors import FieldbusError
from sim_slaves.ethercat import veth
from sim_slaves.ethercat.runner import send_control

PDO_MAPS = Path(__file__).resolve().parents[2] / "pdo_maps"
ALIAS = "fieldbus-veth:"


# -- helpers: links made behind the module's back, as another process would ----------------------


def _link(name: str) -> tuple[int, str | None] | None:
    """(ifindex, alias) of link ``name``, None when there is none."""
    res = subprocess.run(["ip", "-o", "link", "show", "dev", name], capture_output=True, text=True)
    if res.returncode != 0 or not res.stdout:
        return None
    line = res.stdout.splitlines()[0]
    alias = line.split(" alias ", 1)[1].split()[0] if " alias " in line else None
    return int(line.split(":", 1)[0]), alias


def _add_pair(master: str, alias: str | None) -> None:
    slave = "fbs" + master[3:]
    subprocess.run(["ip", "link", "add", master, "type", "veth", "peer", "name", slave], check=True)
    if alias is not None:
        subprocess.run(["ip", "link", "set", master, "alias", alias], check=True)


def _start_ticks(pid: int) -> int:
    return int((Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split())[19])


def _pidns() -> int:
    return os.stat("/proc/self/ns/pid").st_ino


def _owner_alias(pid: int, *, start: int | None = None, pidns: int | None = None) -> str:
    """The documented alias ``fieldbus-veth:<pid>:<start ticks>:<pid namespace inode>``."""
    start = _start_ticks(pid) if start is None else start
    return f"{ALIAS}{pid}:{start}:{_pidns() if pidns is None else pidns}"


def _dead_pid() -> int:
    proc = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True
    )
    pid = int(proc.stdout)
    if Path(f"/proc/{pid}").exists():
        pytest.skip(f"pid {pid} of an exited process was reused at once")
    return pid


@pytest.fixture
def veth_ok() -> None:
    """Skip, with the machine's reason, where veth pairs cannot be made."""
    try:
        master, _ = veth.make_veth_pair()
    except veth.VethUnavailable as exc:
        pytest.skip(str(exc))
    veth.delete_link(master)


@pytest.fixture
def links() -> Iterator[list[str]]:
    """Names appended here are deleted afterwards (whoever made them)."""
    made: list[str] = []
    yield made
    for name in made:
        subprocess.run(["ip", "link", "del", name], capture_output=True)


@pytest.fixture
def other_process() -> Iterator[subprocess.Popen[str]]:
    """A live process standing for another user of the emulator."""
    proc = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(600)"], text=True)
    yield proc
    proc.kill()
    proc.wait(5)


# -- (a) a live pair of another process is never deleted ----------------------------------------


def test_a_live_pair_with_the_name_we_draw_is_never_deleted(
    veth_ok: None, links: list[str], other_process: subprocess.Popen[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Another (live) process creates a pair with exactly the name make_veth_pair is about to use.

    The other pair appears the moment this process first touches that name
    (``ip link del`` or ``ip link add``): whatever the generator picks, it
    collides. The other pair must survive with its ifindex and alias, and we
    must get a different name.
    """
    theirs: dict[str, tuple[int, str | None]] = {}
    real_ip = veth._ip

    def ip_with_a_rival(*args: str) -> subprocess.CompletedProcess[str]:
        names = [a for a in args if a.startswith("fbm")]
        if not theirs and names and ("add" in args or "del" in args):
            _add_pair(names[0], _owner_alias(other_process.pid))
            links.append(names[0])
            link = _link(names[0])
            assert link is not None
            theirs[names[0]] = link
        return real_ip(*args)

    monkeypatch.setattr(veth, "_ip", ip_with_a_rival)
    master, slave = veth.make_veth_pair()
    links.append(master)
    monkeypatch.undo()

    [(name, before)] = theirs.items()
    assert _link(name) == before, f"the other process's live pair {name} was deleted or replaced"
    assert master != name and slave != "fbs" + name[3:]
    assert len(master) <= 15 and len(slave) <= 15  # IFNAMSIZ 16 with the NUL
    assert veth.owner_pid(master) == os.getpid()


def _spawn_at_pid(pid: int, args: list[str]) -> subprocess.Popen[str] | None:
    """Start ``args`` as process ``pid`` (the kernel's next pid set through ns_last_pid), None if it lands elsewhere."""
    for _ in range(5):
        try:
            Path("/proc/sys/kernel/ns_last_pid").write_text(str(pid - 1))
        except OSError as exc:
            pytest.skip(f"cannot choose the next pid (/proc/sys/kernel/ns_last_pid: {exc})")
        proc = subprocess.Popen(args, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        if proc.pid == pid:
            return proc
        proc.kill()  # another fork took it: try again
        proc.wait(5)
    return None


HOLD = (
    "import sys\n"
    "from sim_slaves.ethercat import veth\n"
    "m, s = veth.make_veth_pair()\n"
    "print(m, flush=True)\n"
    "sys.stdin.read()\n"
    "veth.delete_link(m)\n"
)


def test_two_processes_whose_pids_differ_by_1000_keep_their_pairs(veth_ok: None, links: list[str]) -> None:
    """Two real processes, pids P and P + 1000, each make a pair and hold it: both pairs stay theirs."""
    first = subprocess.Popen(
        [sys.executable, "-c", HOLD], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    second: subprocess.Popen[str] | None = None
    try:
        assert first.stdout is not None
        theirs = first.stdout.readline().strip()
        links.append(theirs)
        before = _link(theirs)
        assert before is not None
        pid_max = int(Path("/proc/sys/kernel/pid_max").read_text())
        target = first.pid + 1000 if first.pid + 1000 < pid_max else first.pid - 1000
        if Path(f"/proc/{target}").exists():
            pytest.skip(f"pid {target} (= {first.pid} +- 1000) is in use")
        second = _spawn_at_pid(target, [sys.executable, "-c", HOLD])
        if second is None:
            pytest.skip(f"could not start a process at pid {target}: other processes kept taking it")
        assert second.stdout is not None
        mine = second.stdout.readline().strip()
        links.append(mine)
        assert _link(theirs) == before, (
            f"process {second.pid} deleted the live pair {theirs} of process {first.pid}"
        )
        assert mine and mine != theirs
        assert veth.owner_pid(theirs) == first.pid and veth.owner_pid(mine) == second.pid
        for proc, name in ((first, theirs), (second, mine)):
            assert proc.stdin is not None
            proc.stdin.close()
            assert proc.wait(10) == 0
            assert _link(name) is None  # each owner deleted its own pair
    finally:
        for proc in filter(None, (first, second)):
            proc.kill()
            proc.wait(5)


# -- (b) pairs of dead processes are removed, nothing else -------------------------------------


def test_pairs_of_dead_processes_are_removed_all_others_stay(
    veth_ok: None, links: list[str], other_process: subprocess.Popen[str]
) -> None:
    dead, live = _dead_pid(), other_process.pid
    tag = secrets.token_hex(2)
    doomed = {
        f"fbm{tag}d0": _owner_alias(dead, start=12345),  # owner's pid gone
        f"fbm{tag}d1": f"{ALIAS}{dead}",  # the earlier pid-only alias, pid gone
        f"fbm{tag}d2": _owner_alias(live, start=_start_ticks(live) + 1),  # pid reused by a later process
    }
    kept = {
        f"fbm{tag}k0": _owner_alias(live),  # owner alive
        f"fbm{tag}k1": _owner_alias(dead, start=12345, pidns=_pidns() + 1),  # another pid namespace
        f"fbm{tag}k2": None,  # no alias: not provably ours
        f"fbm{tag}k3": "someone-else:1",  # another alias: not ours
        f"fbm{tag}k4": f"{ALIAS}{live}",  # pid-only alias, pid alive
    }
    for name, alias in {**doomed, **kept}.items():
        _add_pair(name, alias)
        links.append(name)
    before = {name: _link(name) for name in kept}

    master, _ = veth.make_veth_pair()  # cleans up first
    links.append(master)

    assert {name: _link(name) for name in doomed} == dict.fromkeys(doomed)
    assert {name: _link(name) for name in kept} == before
    for name in doomed:
        assert _link("fbs" + name[3:]) is None  # the peer went with it


# -- (c) a runner's stderr cannot fill up -------------------------------------------------------

# A stand-in runner: ready at once, then for each control datagram ~64 KiB to stderr, then the answer.
CHATTY = r"""
import json, socket, sys
s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
s.bind(sys.argv[1])
print("ready standin 0 slaves", flush=True)
line = "dropped malformed frame: " + "x" * 999 + "\n"
n = 0
while True:
    msg, addr = s.recvfrom(65536)
    sys.stderr.write(line * 64)
    sys.stderr.flush()
    n += 1
    s.sendto(json.dumps({"ok": True, "n": n}).encode(), addr)
"""


def test_a_runner_writing_megabytes_to_stderr_keeps_answering(tmp_path: Path) -> None:
    control = tmp_path / "ctl.sock"
    proc = veth.start_runner(
        "standin", [], control=control, command=[sys.executable, "-c", CHATTY, str(control)]
    )
    try:
        for i in range(1, 33):  # 32 x 64 KiB = 2 MiB of stderr
            try:
                answer = send_control(control, {"cmd": "status"}, timeout_s=5.0)
            except TimeoutError:
                pytest.fail(f"no answer to command {i} (stderr so far: {i * 64} KiB): the runner is blocked")
            assert answer == {"ok": True, "n": i}
        assert proc.poll() is None
    finally:
        proc.kill()
        proc.wait(5)


def test_a_runner_that_floods_stderr_and_fails_reports_its_last_words(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(veth, "READY_TIMEOUT_S", 10.0)
    script = (
        "import sys\n"
        "sys.stderr.write(('noise ' + 'x' * 100 + '\\n') * 20000)\n"  # 2 MiB before failing
        "sys.exit('fatal: no such interface: standin')\n"
    )
    t0 = time.monotonic()
    with pytest.raises(FieldbusError, match="fatal: no such interface: standin"):
        veth.start_runner(
            "standin", [], control=tmp_path / "ctl.sock", command=[sys.executable, "-c", script]
        )
    assert time.monotonic() - t0 < 8.0  # noticed when it exited, not at the timeout


def test_the_real_emulator_flooded_with_malformed_frames_keeps_answering(
    veth_ok: None, tmp_path: Path
) -> None:
    """Every malformed frame costs the runner a stderr line; > 1 MiB of them and it still answers."""
    # EtherCAT header announcing 2047 bytes in a 60-byte frame: ~80 bytes of stderr each
    frame = b"\xff" * 6 + b"\x02\x00\x00\x00\x00\x01" + b"\x88\xa4" + struct.pack("<H", 0x1000 | 0x7FF)
    frame += bytes(60 - len(frame))
    with veth.emulated_segment([PDO_MAPS / "generic_cia402.yaml"], workdir=tmp_path) as emu:
        stderr = getattr(emu, "stderr", None)  # the file the runner writes (absent: a pipe)
        sock = socket.socket(socket.AF_PACKET, socket.SOCK_RAW)
        sock.bind((emu.iface, 0))
        sent, deadline = 0, time.monotonic() + 60.0
        try:
            # bursts of 50 paced by a status command (the kernel drops what the runner cannot take),
            # until its stderr holds 1 MiB
            while (stderr.stat().st_size if stderr is not None else 0) <= 1 << 20:
                assert time.monotonic() < deadline, f"stderr still under 1 MiB after {sent} malformed frames"
                for _ in range(50):
                    sock.send(frame)
                sent += 50
                try:
                    answer = emu.command(cmd="status")
                except TimeoutError:
                    pytest.fail(f"the emulator stopped answering after {sent} malformed frames")
                assert answer["ok"] is True
        finally:
            sock.close()
        assert emu.proc.poll() is None
        assert stderr is not None and "EtherCAT header announces 2047 bytes" in stderr.read_text()
