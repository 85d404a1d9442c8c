"""veth pairs for the emulator: unique names, a live pair is never deleted by another process,
orphans of dead processes are cleaned, and a chatty runner never blocks on its stderr."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from sim_slaves.ethercat import veth
from sim_slaves.ethercat.veth import VethUnavailable, delete_link, make_veth_pair, owner_pid

pytestmark = pytest.mark.veth


@pytest.fixture
def pair() -> Iterator[tuple[str, str]]:
    try:
        master, slave = make_veth_pair()
    except VethUnavailable as exc:
        pytest.skip(str(exc))
    yield master, slave
    delete_link(master)


def _exists(name: str) -> bool:
    return subprocess.run(["ip", "link", "show", name], capture_output=True).returncode == 0


def test_a_pair_is_owned_by_its_process_and_names_do_not_repeat(pair: tuple[str, str]) -> None:
    master = pair[0]
    assert owner_pid(master) == os.getpid()
    names = set()
    for _ in range(5):
        m, _s = make_veth_pair()
        names.add(m)
        delete_link(m)
    assert len(names) == 5 and master not in names


def test_another_process_never_deletes_a_live_pair(pair: tuple[str, str]) -> None:
    """A second process drawing the same name gets another one, and our pair stays up."""
    master, slave = pair
    tag = master[3:]  # the other process's first two draws collide with our live pair
    code = (
        "import secrets, sys\n"
        "from sim_slaves.ethercat import veth\n"
        f"draws = iter({[tag, tag, 'c0ffee']!r})\n"
        "secrets.token_hex = lambda n: next(draws)\n"
        "m, s = veth.make_veth_pair()\n"
        "print(m)\n"
        "veth.delete_link(m)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "fbmc0ffee"
    assert _exists(master) and _exists(slave) and owner_pid(master) == os.getpid()


def test_pairs_of_dead_processes_are_removed_live_ones_kept(pair: tuple[str, str]) -> None:
    proc = subprocess.run(
        [sys.executable, "-c", "from sim_slaves.ethercat import veth; print(veth.make_veth_pair()[0])"],
        capture_output=True,
        text=True,
        check=True,
    )
    orphan = proc.stdout.strip()  # its owner has exited without deleting it
    assert _exists(orphan)
    removed = veth.remove_orphaned_pairs()
    assert orphan in removed and not _exists(orphan)
    assert _exists(pair[0])  # ours (alive) stays


def test_a_runner_that_writes_megabytes_to_stderr_keeps_running(tmp_path: Path) -> None:
    """The emulator prints one stderr line per malformed frame; 64 KiB unread in a pipe would stop it."""
    script = (
        "import sys, time\n"
        "print('ready x 0 slaves', flush=True)\n"
        "for i in range(20000):\n"
        "    print('dropped malformed frame: ' + 'x' * 80, file=sys.stderr, flush=True)\n"
        "print('done', flush=True)\n"
        "time.sleep(30)\n"
    )
    err = tmp_path / "runner.err"
    proc = veth.start_runner(
        "x", [], control=tmp_path / "ctl.sock", stderr=err, command=[sys.executable, "-c", script]
    )
    try:
        assert proc.stdout is not None
        deadline = time.monotonic() + 20
        line = ""
        while time.monotonic() < deadline and line != "done\n":
            line = proc.stdout.readline()
        assert line == "done\n", "the runner blocked writing its stderr"
        assert err.stat().st_size > 1_500_000
    finally:
        proc.kill()
        proc.wait(5)


def test_a_runner_that_fails_to_start_reports_its_stderr(tmp_path: Path) -> None:
    script = "import sys; print('no such interface: x', file=sys.stderr); sys.exit(2)"
    with pytest.raises(Exception, match="no such interface: x"):
        veth.start_runner("x", [], control=tmp_path / "ctl.sock", command=[sys.executable, "-c", script])
