"""AcyclicModes alone, its transfers answered by hand (a stand-in for the network's acyclic queue).

Only our own code on both sides here; the bus tests (sim, CANopen emulator, veth with tshark) judge
the transfers themselves.
"""

from __future__ import annotations

from concurrent.futures import Future

import pytest

from fieldbus.core.acyclic_modes import AcyclicModeError, AcyclicModes
from fieldbus.errors import FieldbusError


class _Queue:
    def __init__(self) -> None:
        self.sent: list[tuple[str, int, bytes | None, Future[bytes | None]]] = []

    def submit(self, slave: str, index: int, sub_index: int, data: bytes | None) -> Future[bytes | None]:
        f: Future[bytes | None] = Future()
        self.sent.append((slave, index, data, f))
        return f


def test_a_request_is_one_download_then_uploads_until_the_display_follows() -> None:
    q = _Queue()
    modes = AcyclicModes([("j0", 0x6060), ("j0", 0x6860)], q.submit)  # axis 2 of a two-axis slave
    modes.request[:] = 8
    modes.step()
    assert [(s, i, d) for s, i, d, _ in q.sent] == [("j0", 0x6060, b"\x08"), ("j0", 0x6860, b"\x08")]
    modes.step()  # nothing answered yet: nothing more queued (one transfer per axis at a time)
    assert len(q.sent) == 2
    for *_, f in q.sent:
        f.set_result(None)
    modes.step()
    assert [(i, d) for _, i, d, _ in q.sent[2:]] == [(0x6061, None), (0x6861, None)]
    q.sent[2][3].set_result(b"\x00")  # axis 1 not switched yet
    q.sent[3][3].set_result(b"\x08")
    modes.step()
    assert list(modes.display) == [0, 8] and [(i, d) for _, i, d, _ in q.sent[4:]] == [(0x6061, None)]
    q.sent[4][3].set_result(b"\x08")
    modes.step()
    assert modes.settled and list(modes.writes) == [1, 1] and list(modes.reads) == [2, 1]
    modes.step()
    assert len(q.sent) == 5  # settled: nothing sent


def test_a_failed_download_names_the_axis_and_object() -> None:
    q = _Queue()
    modes = AcyclicModes([("knee", 0x6060)], q.submit)
    modes.request[:] = 9
    modes.step()
    q.sent[0][3].set_exception(FieldbusError("SDO abort 0x06090030 (value out of range)"))
    with pytest.raises(AcyclicModeError, match=r"knee \(row 0\): SDO 0x6060 failed: .*0x06090030"):
        modes.step()
    modes.step()  # written again on the next step
    assert [d for _, _, d, _ in q.sent] == [b"\x09", b"\x09"]


def test_a_recovery_forgets_the_display_and_a_changed_mode_is_written_again() -> None:
    """A recovery of the bus (a slave power-cycled: back in its start-up mode) forgets the display;
    the read that follows decides: the request shown, nothing written; another mode, 0x6060 written
    again. An answer to a transfer asked before the recovery counts no more."""
    import numpy as np

    from fieldbus.core.acyclic_modes import UNKNOWN_MODE

    q = _Queue()
    recoveries = [0]
    modes = AcyclicModes([("j0", 0x6060)], q.submit, lambda: recoveries[0])
    modes.request[:] = 9
    modes.step()
    q.sent[-1][3].set_result(None)
    modes.step()
    q.sent[-1][3].set_result(b"\x09")
    modes.step()
    assert modes.settled and list(modes.writes) == [1]
    recoveries[0] += 1  # the bus brought a slave back: the display is forgotten, the next read decides
    modes.step()
    assert modes.display[0] == UNKNOWN_MODE and not modes.settled and modes.forgotten[0] == 1
    assert q.sent[-1][1:3] == (0x6061, None)
    early = q.sent[-1][3]
    recoveries[0] += 1  # another recovery: forgotten again; the read in flight is now obsolete
    modes.step()
    early.set_result(b"\x09")  # asked during the outage: does not count
    modes.step()
    assert modes.display[0] == UNKNOWN_MODE and q.sent[-1][1:3] == (0x6061, None)
    q.sent[-1][3].set_result(b"\x08")  # the drive came back in CSP (its start-up SDO)
    modes.step()
    assert q.sent[-1][1:3] == (0x6060, b"\x09") and list(modes.writes) == [2]  # ours, again
    q.sent[-1][3].set_result(None)
    modes.step()
    q.sent[-1][3].set_result(b"\x09")
    modes.step()
    assert modes.settled and modes.display[0] == 9
    modes.forget(np.ones(1, dtype=bool))  # e.g. the axis left OPERATION ENABLED
    modes.step()
    q.sent[-1][3].set_result(b"\x09")  # still in our mode: nothing written
    modes.step()
    assert modes.settled and list(modes.writes) == [2]
