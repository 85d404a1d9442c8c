"""Working-counter policy: verdicts, held inputs, safe stop exactly at the threshold."""

from __future__ import annotations

import numpy as np
import pytest

from fieldbus.core.al import AL_ERROR, AL_INIT, AL_OP, AL_PREOP, AL_SAFEOP
from fieldbus.core.pdo import drive_map_from_text
from fieldbus.core.pdo.layout import layout
from fieldbus.core.wkc import (
    PolicyConfig,
    Recovery,
    Verdict,
    WkcPolicy,
    expected_wkc,
    recovery_action,
)
from fieldbus.platform.allocs import net_blocks

BOTH = "vendor_id: 1\nproduct_id: 1\nrpdo: [{index: 0x1600, channels: [{index: 0x6040, sub_index: 0, type: uint16}]}]\ntpdo: [{index: 0x1a00, channels: [{index: 0x6041, sub_index: 0, type: uint16}]}]\n"
IN_ONLY = "vendor_id: 1\nproduct_id: 1\ntpdo: [{index: 0x1a00, channels: [{index: 0x6000, sub_index: 1, type: bool}]}]\n"


def test_expected_wkc_counts_2_per_output_slave_and_1_per_input_slave() -> None:
    both, inp = layout(drive_map_from_text(BOTH)), layout(drive_map_from_text(IN_ONLY))
    assert expected_wkc([both] * 12) == 36
    assert expected_wkc([both, inp, inp]) == 5


def test_verdicts_and_stale_flags() -> None:
    p = WkcPolicy(expected=6, n_slaves=2)
    assert p.judge(6) is Verdict.OK and p.fresh.all()
    assert p.judge(5) is Verdict.SHORT and not p.fresh.any()
    assert p.judge(None) is Verdict.TIMEOUT and not p.fresh.any()
    assert p.judge(-1) is Verdict.TIMEOUT
    assert p.judge(7) is Verdict.SHORT  # too big is as wrong as too small
    assert list(p.stale_cycles) == [4, 4]
    assert p.judge(6) is Verdict.OK and list(p.stale_cycles) == [0, 0]
    s = p.stats
    assert (s.cycles, s.misses, s.timeouts, s.short, s.longest_streak, s.recoveries) == (6, 4, 2, 2, 4, 1)


def test_per_slave_arrival_on_can() -> None:
    p = WkcPolicy(expected=3, n_slaves=3)
    assert p.judge(2, np.array([True, False, True])) is Verdict.SHORT
    assert list(p.fresh) == [True, False, True]
    assert list(p.stale_cycles) == [0, 1, 0]
    assert p.judge(None, np.array([False, False, False])) is Verdict.TIMEOUT and not p.fresh.any()
    assert p.judge(3, np.array([True, True, True])) is Verdict.OK and p.fresh.all()


@pytest.mark.parametrize("threshold", [1, 3, 10])
def test_safe_stop_fires_exactly_at_threshold(threshold: int) -> None:
    p = WkcPolicy(expected=3, n_slaves=1, config=PolicyConfig(safe_stop_after=threshold))
    for i in range(1, threshold):
        p.judge(None)
        assert not p.safe_stop, f"fired after {i} misses"
    p.judge(2)
    assert p.safe_stop and p.stats.safe_stops == 1
    p.judge(3)  # a good cycle does not release the latch
    assert p.safe_stop and p.consecutive_misses == 0
    assert not p.clear_safe_stop()  # asked: it opens after release_after fresh cycles in a row
    for _ in range(p.config.release_after - 2):
        p.judge(3)
        assert p.safe_stop
    p.judge(3)
    assert not p.safe_stop and p.stats.releases == 1


def test_default_threshold_is_the_seeds_10() -> None:
    assert PolicyConfig().safe_stop_after == 10
    with pytest.raises(ValueError):
        PolicyConfig(safe_stop_after=0)


def test_judge_allocates_nothing() -> None:
    p = WkcPolicy(expected=36, n_slaves=12)
    seq = iter(range(10**9))
    assert net_blocks(lambda: p.judge(36 if next(seq) % 7 else None), cycles=5000) <= 2


def test_recovery_actions_follow_ecatcheck() -> None:
    assert recovery_action(AL_OP) is Recovery.NONE
    assert recovery_action(AL_SAFEOP | AL_ERROR) is Recovery.ACK_ERROR
    assert recovery_action(AL_SAFEOP) is Recovery.REQUEST_OP
    assert recovery_action(AL_INIT) is Recovery.RECONFIGURE
    assert recovery_action(AL_PREOP) is Recovery.RECONFIGURE
    assert recovery_action(None) is Recovery.RECOVER


def test_a_short_working_counter_is_attributed_only_when_the_al_readings_account_for_it() -> None:
    """The wind-down's per-slave rule (S6): OP slaves' weights must sum to the counter exactly."""
    from fieldbus.core.al import AL_BOOT
    from fieldbus.core.wkc import AL_UNREAD, answered_slaves

    w = [3, 3, 1]
    assert answered_slaves(4, w, [AL_OP, None, AL_OP]) == [True, False, True]  # slave 1 power-cycled
    assert answered_slaves(3, w, [AL_OP, AL_INIT, AL_PREOP]) == [True, False, False]
    assert answered_slaves(4, w, [AL_OP, AL_BOOT | AL_ERROR, AL_OP]) == [True, False, True]
    assert answered_slaves(5, w, [AL_OP, None, AL_OP]) is None  # the counter says otherwise
    assert answered_slaves(4, w, [AL_OP, AL_SAFEOP, AL_OP]) is None  # SAFE-OP may add its read
    assert answered_slaves(4, w, [AL_OP, AL_OP | AL_ERROR, AL_INIT]) is None  # OP with an error
    assert answered_slaves(4, w, [AL_OP, AL_UNREAD, AL_OP]) is None  # not read in this recovery
    assert answered_slaves(None, w, [AL_OP, None, AL_OP]) is None  # no reply at all
    assert answered_slaves(4, w, [AL_OP, None]) is None
