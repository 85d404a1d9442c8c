"""``sdo_read``/``sdo_write`` in OP from another thread: what the caller is told when the cycle fails or never serves."""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from fieldbus.commands.demo import demo_network
from fieldbus.errors import BusTimeoutError
from fieldbus.network import Operational, open_network

FOLLOWING_ERROR_WINDOW = 0x6065  # UNSIGNED32, not in a PDO: only SDO writes change it


@pytest.fixture
def op(tmp_path: Path) -> Iterator[Operational]:
    """Two demo joints on the in-process EtherCAT emulator, in OP."""
    with (
        demo_network("sim", 2, 1000.0, tmp_path) as setup,
        open_network(setup.net_file, backend="sim") as net,
    ):
        yield net.bring_up()


def _in_thread(call: Callable[[], Any], op: Operational | None) -> Any:
    """``call`` in another thread while this one runs the cycle (``op``; None: no cycle); its result or error."""
    out: list[Any] = []

    def run() -> None:
        try:
            out.append(call())
        except Exception as exc:
            out.append(exc)

    thread = threading.Thread(target=run)
    thread.start()
    while thread.is_alive():
        if op is not None:
            op.exchange()
    thread.join()
    (got,) = out
    return got


def test_a_transfer_that_times_out_on_the_wire_is_reported_as_that(
    op: Operational, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A drive that does not answer in the cycle's budget fails the transfer with its own
    BusTimeoutError; that it is a TimeoutError too must not make it read as "not served"."""
    backend: Any = op._net.backends[0]
    backend.chain.mute_mailbox(1)  # j1's mailbox drops every request: the transfer runs out of cycles
    err = _in_thread(lambda: op.sdo_read("joints", "j1", 0x1018, 1, timeout_s=30.0), op)
    assert isinstance(err, BusTimeoutError) and "SDO read 0x1018:01 not complete in" in str(err), err
    assert "not served" not in str(err)


def test_a_transfer_not_served_in_time_is_withdrawn_and_never_applied(op: Operational) -> None:
    """Nobody runs the cycle: the write times out, and it is not applied by a later cycle either."""
    window = FOLLOWING_ERROR_WINDOW
    before = _in_thread(lambda: op.sdo_read("joints", "j1", window, 0, timeout_s=5.0), op)
    other = (int.from_bytes(before, "little") + 1000).to_bytes(4, "little")
    err = _in_thread(lambda: op.sdo_write("joints", "j1", window, 0, other, timeout_s=0.05), None)
    assert isinstance(err, BusTimeoutError) and "not served within 0.05 s (withdrawn)" in str(err), err
    for _ in range(5):
        op.exchange()
    after = _in_thread(lambda: op.sdo_read("joints", "j1", window, 0, timeout_s=5.0), op)
    assert after == before, (before, after)  # the withdrawn write never ran
    _in_thread(lambda: op.sdo_write("joints", "j1", window, 0, other, timeout_s=5.0), op)
    assert _in_thread(lambda: op.sdo_read("joints", "j1", window, 0, timeout_s=5.0), op) == other  # writable
