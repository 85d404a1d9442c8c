"""The command gate of ``fieldbus serve``, in cycles: one owner, ordered sequences, hold then a latched stop."""

from __future__ import annotations

import pytest

from fieldbus.dds.gate import ClaimError, CommandGate, Deadline, GateState
from fieldbus.errors import FieldbusError


def _gate(hold: int = 3, stop: int = 6) -> CommandGate:
    g = CommandGate(Deadline(hold, stop))
    g.claim("a")
    return g


def test_second_claimer_refused_while_the_owner_is_alive_naming_the_owner() -> None:
    g = _gate()
    with pytest.raises(ClaimError, match="'a'"):
        g.claim("b")
    g.claim("a")  # the owner again: fine
    assert g.owner == "a"


def test_commands_from_a_non_owner_are_refused_and_counted() -> None:
    g = _gate()
    assert not g.offer("b", 1)
    assert g.refused == 1 and g.applied_sequence == 0


def test_a_sequence_that_does_not_increase_is_dropped_and_counted() -> None:
    g = _gate()
    assert g.offer("a", 5)
    assert not g.offer("a", 5)
    assert not g.offer("a", 4)
    assert g.offer("a", 6)
    assert (g.dropped, g.applied_sequence) == (2, 6)


def test_hold_after_n_then_safe_stop_after_m_cycles_latched_until_clear() -> None:
    g = _gate(hold=3, stop=6)
    assert g.tick() is GateState.IDLE  # no deadline before the first command
    g.offer("a", 1)
    states = [g.tick() for _ in range(10)]
    assert states[0] is GateState.COMMANDED
    assert states[1:3] == [GateState.COMMANDED] * 2  # ages 1, 2
    assert states[3:6] == [GateState.HOLD] * 3  # ages 3, 4, 5
    assert states[6:] == [GateState.SAFE_STOP] * 4  # age 6 and after: latched
    assert not g.offer("a", 2)  # a late command does not open the latch
    assert g.tick() is GateState.SAFE_STOP
    with pytest.raises(ClaimError):
        g.clear("b")
    g.clear("a")
    assert g.tick() is GateState.IDLE
    assert g.offer("a", 3) and g.tick() is GateState.COMMANDED


def test_a_new_claim_is_possible_only_after_the_owner_latched_and_restarts_the_sequence() -> None:
    g = _gate(hold=1, stop=2)
    g.offer("a", 100)
    for _ in range(3):
        g.tick()
    assert g.latched
    g.claim("b")  # the owner's deadline fired: a restarted controller may take over
    assert g.latched  # but the latch stays until b clears it
    g.clear("b")
    assert g.offer("b", 1)  # a new owner's sequence starts again


@pytest.mark.parametrize(("hold", "stop"), [(0, 5), (5, 5), (6, 5), (True, 5)])
def test_bad_deadlines_are_refused(hold: int, stop: int) -> None:
    with pytest.raises(FieldbusError, match="deadline"):
        Deadline(hold, stop)


def test_an_owner_that_never_commands_latches_after_stop_after_cycles_and_the_group_is_claimable() -> None:
    g = _gate(hold=3, stop=6)  # claimed by 'a', no command
    states = [g.tick() for _ in range(7)]
    assert states[:5] == [GateState.IDLE] * 5  # no HOLD from IDLE: nothing is applied to hold
    assert states[5:] == [GateState.SAFE_STOP] * 2  # the 6th cycle without a command
    g.claim("b")  # claimable again


def test_a_request_from_the_owner_restarts_the_idle_deadline_a_paused_gate_does_not_age() -> None:
    g = _gate(hold=3, stop=6)
    for _ in range(5):
        g.tick()
    g.heard_from("b")  # not the owner: nothing
    g.heard_from("a")
    assert [g.tick() for _ in range(5)] == [GateState.IDLE] * 5
    g.pause("a")  # homing, a mode switch, an enable under way
    assert [g.tick() for _ in range(20)] == [GateState.IDLE] * 20
    g.resume()
    assert [g.tick() for _ in range(6)][-1] is GateState.SAFE_STOP


def test_a_latch_from_outside_holds_until_the_owner_clears_and_a_clear_applies_no_command() -> None:
    g = _gate()
    assert g.offer("a", 1) and g.tick() is GateState.COMMANDED
    g.latch()  # the bus's safe stop or a drive fault
    assert not g.offer("a", 2) and g.tick() is GateState.SAFE_STOP
    g.clear("a")
    assert g.tick() is GateState.IDLE  # nothing applies until the next command
