"""Fault specs and schedules of the soak harness (pure)."""

from __future__ import annotations

import random

import pytest

from fieldbus.operations.soak import FaultSpec, FaultSpecError, schedule


def test_parse_full_spec() -> None:
    s = FaultSpec.parse("loss=0.01, delay=0.002,wkc=0.003,power_cycles=3,bursts=2,sdo_aborts=1")
    assert s == FaultSpec(0.01, 0.002, 0.003, 3, 2, 1)
    assert FaultSpec.parse("") == FaultSpec()


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ("loss", "kind=value"),
        ("lost=0.1", "expected one of"),
        ("loss=x", "not a number"),
        ("loss=0.9", "0..0.5"),
        ("power_cycles=-1", ">= 0"),
        ("bursts=1.5", "not a number"),
    ],
)
def test_parse_errors_name_the_bad_part(text: str, needle: str) -> None:
    with pytest.raises(FaultSpecError, match=needle):
        FaultSpec.parse(text)


def test_schedule_spreads_counted_faults_and_draws_rates() -> None:
    spec = FaultSpec(loss=0.01, power_cycles=3, bursts=1)
    plan = schedule(spec, 100_000, 12, random.Random(0), warmup=200)
    kinds = [k for k, _ in plan.values()]
    assert kinds.count("power_cycle") == 3 and kinds.count("burst") == 1
    assert 800 < kinds.count("loss") < 1200  # 1 % of 99,800 cycles
    assert min(plan) >= 200 and max(plan) < 100_000
    assert all(0 <= s < 12 for _, s in plan.values())
    assert plan == schedule(spec, 100_000, 12, random.Random(0), warmup=200)  # seeded: reproducible
