"""soem_iomap.locate: a layout it cannot prove gives None and leaves the per-slave path its outputs.

Only our own code here (a stand-in master without SOEM's IO map); the proof on the real pysoem is
tests/integration/test_ethercat_iomap.py (over veth).
"""

from __future__ import annotations

from fieldbus.backends import soem_iomap


class _Slave:
    """pysoem's slave surface: ``output`` settable with bytes, ``input`` readable."""

    def __init__(self, out: int, inp: int) -> None:
        self.output = bytes(out)
        self.input = bytes(inp)


class _Master:
    """Keeps no IO map inside itself: the pattern written through the slaves is not in its memory."""


def test_an_io_map_that_is_not_inside_the_master_is_not_used() -> None:
    slaves = [_Slave(4, 6), _Slave(4, 6)]
    assert soem_iomap.locate(_Master(), slaves, [(4, 6), (4, 6)]) is None
    assert [s.output for s in slaves] == [bytes(4), bytes(4)]  # the pattern written to find it is cleared


def test_no_outputs_no_pattern_no_view() -> None:
    assert soem_iomap.locate(_Master(), [_Slave(0, 6)], [(0, 6)]) is None
