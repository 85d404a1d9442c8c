"""One master per interface (issue 23, defect 9): a second master on a network card or CAN channel is
refused at open() with "interface 'X' is in use by PID n (program)"; the lock goes with close() and with
its process (the kernel drops a flock when the process dies, even by SIGKILL).

Two processes throughout, except for python-can's ``virtual`` channels, which exist inside one process.
"""

from __future__ import annotations

import itertools
import json
import os
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from fieldbus import PDO_MAPS
from fieldbus.backends import buslock
from fieldbus.backends.buslock import lock_network_card
from fieldbus.commands.demo import DEMO_MAP
from fieldbus.errors import InterfaceInUseError
from fieldbus.network import open_network

pytestmark = pytest.mark.timeout(120)
MIT_MAP = Path(PDO_MAPS) / "cubemars_ak80_9_mit.yaml"
_names = itertools.count()
HOLD = (
    "import sys\n"
    "from fieldbus.backends.buslock import lock_network_card\n"
    "lock = lock_network_card(sys.argv[1])\n"
    "print('locked', flush=True)\n"
    "sys.stdin.read()\n"
)


def _card() -> str:
    return f"fbl{os.getpid() % 100000}x{next(_names)}"  # a name no real card has (and no veth of ours)


@contextmanager
def _holder(card: str) -> Iterator[subprocess.Popen[str]]:
    """Another process holding ``card``'s lock until it is killed."""
    child = subprocess.Popen(
        [sys.executable, "-c", HOLD, card], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    try:
        assert child.stdout is not None and child.stdout.readline() == "locked\n"
        yield child
    finally:
        if child.poll() is None:
            assert child.stdin is not None
            child.stdin.close()  # it lets go as it exits (its lock file removed)
            try:
                child.wait(timeout=20)
            except subprocess.TimeoutExpired:
                child.kill()
                child.wait()


def test_a_second_process_is_refused_and_the_lock_dies_with_its_holder() -> None:
    card = _card()
    with _holder(card) as child:
        with pytest.raises(InterfaceInUseError) as err:
            lock_network_card(card)
        assert err.value.pid == child.pid
        assert (
            str(err.value) == f"interface '{card}' is in use by PID {child.pid} ({Path(sys.executable).name})"
        )
        child.kill()  # SIGKILL: no clean-up of its own; the kernel drops its flock
        child.wait()
        lock = lock_network_card(card)
    assert lock.path is not None and lock.path.read_text().split("\n")[0] == str(os.getpid())
    with pytest.raises(InterfaceInUseError, match=f"in use by PID {os.getpid()}"):
        lock_network_card(card)  # a second open file in this process is refused too
    lock.release()
    assert not lock.path.exists()
    with lock_network_card(card) as again:  # a scan or sdo command holds it this way for its run
        assert again.held
    assert not again.held


def test_the_ethercat_backend_is_refused_a_card_another_master_holds(tmp_path: Path) -> None:
    """Refused at open(), before SOEM touches the card (the card needs not even exist)."""
    pytest.importorskip("pysoem")
    card = _card()
    net_file = tmp_path / "net.yaml"
    net_file.write_text(
        f"buses:\n  - {{name: legs, type: ethercat, interface: {card},\n"
        f"     slaves: [{{name: j0, map: {json.dumps(str(DEMO_MAP))}}}]}}\n"
    )
    with _holder(card) as child, open_network(net_file) as net:
        refused = f"interface '{card}' is in use by PID {child.pid}"
        with pytest.raises(InterfaceInUseError, match=refused):
            net.pre_op()


def test_two_masters_on_one_virtual_channel_in_one_process(tmp_path: Path) -> None:
    """The first keeps the channel until it closes; then the second gets it."""
    channel = f"fb-lock-{os.getpid()}-{next(_names)}"
    net_file = tmp_path / "net.yaml"
    net_file.write_text(
        f"buses:\n  - {{name: legs, type: rawcan, interface: {channel}, can_interface: virtual,\n"
        f"     slaves: [{{name: m0, map: {json.dumps(str(MIT_MAP))}, node_id: 1}}]}}\n"
    )
    refused = f"'virtual {channel}' is in use by PID {os.getpid()}"
    with open_network(net_file) as first:
        first.pre_op()
        with open_network(net_file) as second, pytest.raises(InterfaceInUseError, match=refused):
            second.pre_op()
    with open_network(net_file) as third:
        third.pre_op()  # raw CAN opens without talking to a motor


def test_a_second_fieldbus_run_on_a_channel_in_use_is_refused(tmp_path: Path) -> None:
    """A master in this process on a fieldbus_udp channel (crosses processes, like socketcan); ``fieldbus
    run`` on the same channel exits 1 naming this process, and runs once it closed."""
    pytest.importorskip("can")
    from sim_slaves.can_process import can_emulator_process, udp_bus

    where = udp_bus(7, interface="fieldbus_udp")
    net_file = tmp_path / "legs.yaml"
    net_file.write_text(
        "cycle_time_us: 2000\nreceive_timeout_us: 20000\nsafe_stop_after: 100000\nbuses:\n"
        f"  - {{name: leg, type: rawcan, {where.network_keys()},\n"
        f"     slaves: [{{name: 'm{{i}}', map: {json.dumps(str(MIT_MAP))}, node_id: 1, count: 2}}]}}\n"
    )
    run = [sys.executable, "-m", "fieldbus", "run", str(net_file), "--cycles", "20"]
    port = dict(where.options)["port"]
    with can_emulator_process("mit", MIT_MAP, [1, 2], where, dt_s=0.002):
        with open_network(net_file) as net:
            net.bring_up().exchange()
            second = subprocess.run(run, capture_output=True, text=True, timeout=60)
        assert second.returncode == 1, second.stderr
        assert second.stderr.splitlines()[-1] + "\n" == (  # after the file's own warnings, if any
            f"error: interface 'fieldbus_udp {where.channel}:{port}' is in use by PID {os.getpid()} "
            f"({buslock._program()})\n"
        )
        again = subprocess.run(run, capture_output=True, text=True, timeout=60)
        assert "in use" not in again.stderr and again.returncode in (0, 3), again.stderr  # 3: a miss


def test_lock_files_fall_back_to_the_temp_dir(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    blocker = tmp_path / "not-a-dir"
    blocker.write_text("")
    monkeypatch.setattr(buslock, "LOCK_DIR", blocker / "fieldbus")  # cannot be made
    lock = lock_network_card(_card())
    try:
        assert lock.path is not None and lock.path.parent == Path(tempfile.gettempdir()) / "fieldbus-lock"
    finally:
        lock.release()


def test_scan_and_sdo_are_refused_a_card_a_master_holds(capsys: pytest.CaptureFixture[str]) -> None:
    """A scan (or an SDO access) reconfigures the segment: on a card a master runs on, it is refused first."""
    from fieldbus.cli import main

    card = _card()
    with _holder(card) as child:
        for argv in (["scan", "ethercat", card], ["sdo", "read", "ethercat", card, "0x1000", "0"]):
            assert main(argv) == 1, argv
            err = capsys.readouterr().err
            assert f"interface '{card}' is in use by PID {child.pid}" in err, err
