"""The mailbox step machine (fieldbus.backends.ecat_mailbox) against an emulated ESC's registers.

The port reads and writes the registers of one slave of the ``sim`` backend's
ESC chain (SyncManagers, mailbox RAM, repeat request as an ESC has them) and
can lose a reply before or after the ESC acted on the datagram. Every step
must make at most one port call (one datagram); the over-the-wire proof with
the real pysoem master is tests/integration/test_bounded_steps.py.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from fieldbus.backends.ecat_mailbox import MailboxLayout, SlaveMailbox
from fieldbus.commands.demo import DEMO_MAP
from fieldbus.core.coe_mailbox import SdoTransfer
from fieldbus.errors import BusTimeoutError, SdoAbortError
from fieldbus.network import open_network

IDENTITY = (0xFB1).to_bytes(4, "little")  # the demo drive's 0x1018:1


class EscPort:
    """Registers of one emulated ESC; ``lose``: call numbers whose reply is lost ("before": the datagram
    never reached the ESC; "after": the ESC acted on it, the reply did not come back)."""

    def __init__(self, esc: Any, lose: dict[int, str] | None = None) -> None:
        self.esc = esc
        self.lose = lose or {}
        self.calls: list[tuple[str, int]] = []

    def _lost(self) -> str | None:
        return self.lose.get(len(self.calls) - 1)

    def read(self, ado: int, size: int) -> bytes | None:
        self.calls.append(("read", ado))
        if self._lost() == "before":
            return None
        got: bytes | None = self.esc.read(ado, size, 0)
        return None if self._lost() == "after" else got

    def write(self, ado: int, data: bytes) -> bool:
        self.calls.append(("write", ado))
        if self._lost() == "before":
            return False
        ok: bool = self.esc.write(ado, data, 0)
        return ok and self._lost() != "after"


@pytest.fixture
def esc(tmp_path: Path) -> Iterator[Any]:
    """Slave 1 of three emulated drives brought up to OP on the in-process sim backend."""
    net_file = tmp_path / "net.yaml"
    net_file.write_text(
        "cycle_time_us: 1000\nbuses:\n  - {name: bus, type: ethercat, interface: sim, "
        f"slaves: [{{name: 'j{{i}}', map: {json.dumps(str(DEMO_MAP))}, count: 3}}]}}\n"
    )
    with open_network(net_file, backend="sim") as net:
        net.bring_up()
        yield net.backends[0].chain.slaves[1]  # type: ignore[attr-defined]


def _mailbox(esc: Any, port: EscPort) -> SlaveMailbox:
    layout = MailboxLayout.from_sm_registers(bytes(esc.mem[0x0800:0x0810]))
    assert layout is not None
    return SlaveMailbox(layout, port)


def _run(mbx: SlaveMailbox, port: EscPort, t: SdoTransfer, max_steps: int = 50) -> tuple[Any, int]:
    """Step the transfer to its end; asserts one datagram at most per step; (result, steps)."""
    steps = mbx.transfer(t, max_steps)
    n = 0
    while True:
        before = len(port.calls)
        n += 1
        try:
            next(steps)
        except StopIteration as done:
            assert len(port.calls) - before <= 1, port.calls[before:]
            return done.value, n
        assert len(port.calls) - before <= 1, port.calls[before:]


def test_an_upload_is_a_write_a_status_poll_and_a_read(esc: Any) -> None:
    port = EscPort(esc)
    mbx = _mailbox(esc, port)
    assert _run(mbx, port, SdoTransfer(0x1018, 1, None, mailbox_out=mbx.layout.out_size)) == (IDENTITY, 3)
    assert [c[0] for c in port.calls] == ["write", "read", "read"]
    assert port.calls[1][1] == 0x080D and port.calls[2][1] == mbx.layout.in_start
    assert mbx.counter == 0  # the first request carries 0: SOEM, before, counted 1..7
    _run(mbx, port, SdoTransfer(0x6060, 0, b"\x08", mailbox_out=mbx.layout.out_size))
    assert mbx.counter == 1


def test_a_lost_write_reply_is_sent_again_as_a_repeat_and_executed_once(esc: Any) -> None:
    """After the first request (counter 0, the start value, which a slave never takes for a repeat)."""
    port = EscPort(esc, {3: "after"})
    mbx = _mailbox(esc, port)
    _run(mbx, port, SdoTransfer(0x1018, 1, None, mailbox_out=mbx.layout.out_size))
    requests = esc.mailbox.requests
    got, steps = _run(mbx, port, SdoTransfer(0x1018, 1, None, mailbox_out=mbx.layout.out_size))
    assert got == IDENTITY and steps == 4
    assert esc.mailbox.requests - requests == 1 and esc.mailbox.duplicates == 1  # same counter: a repeat


def test_an_answer_whose_read_reply_is_lost_is_asked_for_again(esc: Any) -> None:
    port = EscPort(esc, {2: "after"})  # the ESC released SM1, the answer never came back
    mbx = _mailbox(esc, port)
    got, _ = _run(mbx, port, SdoTransfer(0x1018, 1, None, mailbox_out=mbx.layout.out_size))
    assert got == IDENTITY and mbx.repeats == 1
    assert ("write", 0x080E) in port.calls  # the repeat request (SM1 activate, bit 1 toggled)
    port2 = EscPort(esc, {2: "before"})  # the read never reached the ESC: read again, no repeat
    mbx2 = _mailbox(esc, port2)
    assert _run(mbx2, port2, SdoTransfer(0x1018, 1, None, mailbox_out=mbx.layout.out_size))[0] == IDENTITY
    assert mbx2.repeats == 0


def test_a_mailbox_that_never_answers_ends_after_its_steps(esc: Any) -> None:
    esc.mailbox_fault = "silent"
    port = EscPort(esc)
    mbx = _mailbox(esc, port)
    with pytest.raises(BusTimeoutError, match="in 30 datagrams"):
        _run(mbx, port, SdoTransfer(0x1018, 1, None, mailbox_out=mbx.layout.out_size), max_steps=30)
    assert len(port.calls) == 30  # one datagram per step, no more
    esc.mailbox_fault = "stuck"  # SM0 stays full: every later write is refused, one per step
    port = EscPort(esc)
    mbx = _mailbox(esc, port)
    with pytest.raises(BusTimeoutError):
        _run(mbx, port, SdoTransfer(0x1018, 1, None, mailbox_out=mbx.layout.out_size), max_steps=10)
    port.calls.clear()
    with pytest.raises(BusTimeoutError):
        _run(mbx, port, SdoTransfer(0x1018, 1, None, mailbox_out=mbx.layout.out_size), max_steps=10)
    assert port.calls == [("write", mbx.layout.out_start)] * 10


def test_emergencies_and_stale_answers_are_set_aside_and_aborts_raise(esc: Any) -> None:
    port = EscPort(esc)
    seen: list[tuple[int, int]] = []
    mbx = _mailbox(esc, port)
    mbx.on_emergency = lambda code, reg: seen.append((code, reg))
    esc.send_emergency(0x8611, 0x81)
    assert _run(mbx, port, SdoTransfer(0x1018, 1, None, mailbox_out=mbx.layout.out_size))[0] == IDENTITY
    assert seen == [(0x8611, 0x81)]
    # an answer left in SM1 by a transfer given up on is dropped, not taken for this one's
    stale = SdoTransfer(0x1018, 2, None, mailbox_out=mbx.layout.out_size)
    steps = mbx.transfer(stale, 50)
    next(steps)  # the request written; never polled
    assert _run(mbx, port, SdoTransfer(0x1018, 1, None, mailbox_out=mbx.layout.out_size))[0] == IDENTITY
    assert mbx.stale_answers == 1
    with pytest.raises(SdoAbortError) as err:
        _run(mbx, port, SdoTransfer(0x5FFF, 0, None, mailbox_out=mbx.layout.out_size))
    assert err.value.code == 0x06020000
