"""ESC error counters: decoding, rises, the cable rule (fieldbus.core.esc_errors) and the emulated faults.

The fault model is our emulator's (sim_slaves' EscChain.bit_errors): these
tests check our rule against our own emulator of the ESC behaviour the
datasheet describes; the counters' layout is checked against the register map.
"""

from __future__ import annotations

import pytest

from fieldbus.commands.demo import DEMO_MAP
from fieldbus.core.ecat import Command, Datagram, build_master_frame
from fieldbus.core.esc_errors import (
    ERRORS_SIZE,
    REG_ERRORS,
    CounterRise,
    DlStatus,
    ErrorWatch,
    EscErrors,
    Link,
    LinkChange,
    PortCounters,
    suspect_links,
)
from fieldbus.core.pdo import load_drive_map
from sim_slaves.ethercat import EscChain


def test_registers_decode_per_port() -> None:
    raw = bytes([1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 0, 0, 15, 16, 17, 18])
    e = EscErrors.from_registers(raw)
    assert e.ports[0] == PortCounters(invalid_frame=1, rx_error=2, forwarded=9, lost_link=15)
    assert e.ports[3] == PortCounters(invalid_frame=7, rx_error=8, forwarded=12, lost_link=18)
    assert (e.processing_unit, e.pdi) == (13, 14)
    assert e.to_registers() == raw


def test_rise_treats_a_lower_value_as_a_reset() -> None:
    a = EscErrors((PortCounters(5), PortCounters(), PortCounters(), PortCounters()))
    b = EscErrors((PortCounters(7), PortCounters(), PortCounters(), PortCounters()))
    assert b.since(a).ports[0].invalid_frame == 2
    assert a.since(b).ports[0].invalid_frame == 5  # cleared in between, then counted 5


def test_rule_origin_not_forwarded() -> None:
    z = PortCounters()
    rises = [
        EscErrors((z, PortCounters(forwarded=9), z, z)),  # slave 0: forwarded only
        EscErrors((z, PortCounters(invalid_frame=2), z, z)),  # slave 1 port 1: cable 1-2
        EscErrors(
            (PortCounters(invalid_frame=3), PortCounters(forwarded=9), z, z)
        ),  # slave 2 port 0: cable 1-2
        EscErrors((PortCounters(forwarded=9), z, z, z)),
    ]
    s = suspect_links(rises)
    assert [x.link for x in s] == [Link(1, 1, 2, 0)] and s[0].errors == 5
    assert (
        s[0].link.describe(["a", "b", "c", "d"]) == "cable between slave 1 (b) port 1 and slave 2 (c) port 0"
    )
    master = suspect_links([EscErrors((PortCounters(rx_error=1), z, z, z))])
    assert master[0].link == Link(None, 1, 0, 0) and "the master" in master[0].link.describe()


def test_dl_status_bits() -> None:
    st = DlStatus(0x0001 | 0x0010 | 0x0200 | 0x0020 | 0x0800 | 0x1000 | 0x4000)
    assert st.pdi_operational and st.link(0) and st.link(1) and not st.link(2)
    assert st.loop_closed(2) and not st.loop_closed(1)
    assert "PDI ok" in st.describe()


def _frames(chain: EscChain, n: int, watch: ErrorWatch | None = None) -> list[object]:
    """n frames of one FPRD each, as a cycle's acyclic datagram; ``watch`` decides what is read."""
    events: list[object] = []
    for k in range(n):
        if watch is None:
            dg = Datagram.physical(Command.BRD, 0, 0x0130, bytes(2))
        else:
            i, reg, size = watch.next_read()
            dg = Datagram.physical(Command.FPRD, chain.slaves[i].station_address, reg, bytes(size))
        reply = chain.process(build_master_frame([dg]), k * 1_000_000)
        if watch is not None:
            data = None
            if reply is not None:
                from fieldbus.core.ecat import decode_frame

                d = decode_frame(reply).datagrams[0]
                data = d.data if d.wkc == 1 else None
            events += watch.feed(data)
    return events


def _chain12() -> EscChain:
    chain = EscChain.from_maps([load_drive_map(DEMO_MAP)] * 12)
    for i, s in enumerate(chain.slaves):
        s.write(0x0010, (0x1001 + i).to_bytes(2, "little"), 0)
    return chain


@pytest.mark.parametrize("seed", [1, 2, 3, 4, 5])
def test_bit_errors_between_slaves_4_and_5_are_located_there(seed: int) -> None:
    chain = _chain12()
    watch = ErrorWatch(12)
    _frames(chain, 48, watch)  # two rounds: every slave's baseline
    chain.bit_errors(4, 0.05, seed=seed)
    events = _frames(chain, 24 * 20, watch)
    assert chain.faults.link_corrupted > 0
    s = watch.suspects()
    assert s and s[0].link == Link(4, 1, 5, 0), s
    assert len(s) == 1  # nothing started anywhere else
    rises = [e for e in events if isinstance(e, CounterRise)]
    assert {e.slave for e in rises if e.rise.ports[0].invalid_frame} == {5}
    assert all(r.suspects[0].link == Link(4, 1, 5, 0) for r in rises if r.suspects)
    # counters as the ESCs hold them: invalid at 5 port 0 (way down) or 4 port 1 (way back), forwarded elsewhere
    raw = [EscErrors.from_registers(s.read(REG_ERRORS, ERRORS_SIZE, 0) or b"") for s in chain.slaves]
    assert all(e.ports[0].invalid_frame == 0 for i, e in enumerate(raw) if i != 5)
    assert all(e.ports[1].invalid_frame == 0 for i, e in enumerate(raw) if i != 4)
    assert raw[11].ports[0].forwarded > 0 and raw[0].ports[1].forwarded > 0


def test_writing_0x0300_clears_the_counters() -> None:
    chain = _chain12()
    chain.bit_errors(4, 1.0, seed=0, frames=10)
    _frames(chain, 10)
    esc = chain.slaves[5]
    assert EscErrors.from_registers(esc.read(REG_ERRORS, ERRORS_SIZE, 0) or b"").ports[0].invalid_frame == 10
    esc.write(REG_ERRORS, b"\x00", 0)  # one byte at 0x0300 clears 0x0300-0x030B
    assert not EscErrors.from_registers(esc.read(REG_ERRORS, ERRORS_SIZE, 0) or b"").any


def test_a_flapping_link_counts_lost_links_at_both_ends_and_is_located() -> None:
    chain = _chain12()
    watch = ErrorWatch(12)
    _frames(chain, 48, watch)
    chain.flap_link(7)
    events = _frames(chain, 48, watch)
    assert watch.suspects()[0].link == Link(7, 1, 8, 0)
    assert watch.since_baseline()[8] is not None
    assert watch.since_baseline()[8].ports[0].lost_link == 1  # type: ignore[union-attr]
    assert not [e for e in events if isinstance(e, LinkChange)]  # back before the next DL status read
    chain.slaves[8].set_link(0, False)
    events = _frames(chain, 48, watch)
    assert any(isinstance(e, LinkChange) and e.slave == 8 and not e.up for e in events)


def test_a_missing_or_short_answer_is_a_missed_read_not_an_error() -> None:
    watch = ErrorWatch(2)
    assert watch.feed(None) == [] and watch.feed(b"\x01") == []  # counters of 0, DL status of 0
    assert watch.feed(bytes(5)) == []  # counters of slave 1: 5 of 20 bytes
    assert watch.missed == 3 and watch.errors == [None, None]
    watch.feed(b"\x11\x02")  # DL status of slave 1
    assert watch.feed(bytes(ERRORS_SIZE)) == []  # slave 0's baseline
    assert watch.errors[0] is not None and watch.suspects() == []
