"""StallWatch counts the served cycle's gaps in the cycle starts it is given (virtual time, ns)."""

from __future__ import annotations

from fieldbus.dds.stalls import StallWatch

MS = 1_000_000


def test_gaps_over_5ms_are_counted_and_those_of_20_periods_are_also_stalls() -> None:
    w = StallWatch(MS)
    starts = [0, 1 * MS, 2 * MS, 7 * MS + MS // 2, 8 * MS + MS // 2, 13 * MS + MS // 2, 35 * MS]
    for cycle, t in enumerate(starts):
        w.tick(t, cycle)
    # gaps: 1, 1, 5.5 (over 5 ms), 1, 5 (not over: 5 ms is the goal itself), 21.5 ms (over, and a stall)
    assert w.over_5ms == 2
    assert w.count == 1 and w.longest_ns == 21 * MS + MS // 2
    assert w.longest_gap_ns == 21 * MS + MS // 2
    # each with the cycle that started late, the gap and when it started (to line up with a witness)
    assert w.over_5ms_at == [(3, 5 * MS + MS // 2, 7 * MS + MS // 2), (6, 21 * MS + MS // 2, 35 * MS)]


def test_the_newest_64_gaps_over_5ms_are_kept_with_their_times() -> None:
    w = StallWatch(MS)
    t = 0
    for cycle in range(100):
        t += 6 * MS
        w.tick(t, cycle)
    assert w.over_5ms == 99 and len(w.over_5ms_at) == 64
    assert w.over_5ms_at[0] == (36, 6 * MS, 37 * 6 * MS) and w.over_5ms_at[-1] == (99, 6 * MS, 100 * 6 * MS)
