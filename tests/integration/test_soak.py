"""Soak: the cycle under injected faults on the emulators; every fault accounted for, no invariant broken.

CI runs 10,000 cycles per backend; docs/reliability.md has the 100,000-cycle
runs and the command that reproduces them.
"""

from __future__ import annotations

import argparse
import os

import pytest

from fieldbus.commands.soak import soak
from fieldbus.runtime.soak import FaultSpec

CYCLES = int(os.environ.get("FIELDBUS_SOAK_CYCLES", "10000"))


def _args(backend: str, **kw: object) -> argparse.Namespace:
    """``fieldbus soak --demo --backend BACKEND`` as the CLI parses it (every flag at its default), then ``kw``."""
    from fieldbus.cli import build_parser

    args = build_parser().parse_args(["soak", "--demo", "--backend", backend])
    args.cycles = CYCLES
    args.seed = 1  # rate stays None: paced at the network's cycle time (1 kHz), as a robot runs
    for key, value in kw.items():
        setattr(args, key, value)
    return args


@pytest.mark.parametrize("backend", ["sim", pytest.param("ethercat", marks=pytest.mark.veth)])
def test_soak_accounts_for_every_fault(backend: str, request: pytest.FixtureRequest) -> None:
    """EtherCAT: frame loss, late replies, WKC errors, power cycles, a loss burst, an SDO abort at bring-up."""
    if backend == "ethercat":
        request.getfixturevalue("veth_possible")
    faults = "loss=0.01,delay=0.001,wkc=0.001,power_cycles=3,bursts=1,sdo_aborts=1"
    # sim: the emulator runs inside exchange(); the cycles after a power-cycled drive comes back
    # rebuild the copy plans and step the bank in stretches (one drive with another step length),
    # up to 2.7 ms on a quiet machine and 6.7 ms once in a loaded full run (before the stretches:
    # one drive at a time) - emulator work, so the sim run gets 10 ms of margin instead of 5.
    # EtherCAT: miss cycles measure max 3.9-4.5 ms alone (timeout 2 ms); one full-suite run on this
    # 2-CPU VM had one at 7.1 ms in 10,000 cycles (cyclictest's own worst wake-up here is 3.5 ms
    # quiet): 7 ms of margin, still far below the 5-10 ms a lost frame cost before issue 12
    extra = {"margin_us": 10_000.0} if backend == "sim" else {"margin_us": 7_000.0}
    r = soak(_args(backend, faults=faults, **extra), FaultSpec.parse(faults))
    assert r["violation_count"] == 0, r["violations"]
    assert r["injected"] == r["detected"]
    assert r["injected"]["power_cycle"] == 3 and r["recovered_power_cycles"] == 3
    assert r["injected"]["sdo_abort"] == 1 and r["injected"]["burst"] == 1
    assert r["injected"]["loss"] > CYCLES * 0.005
    assert r["safe_stops"] >= 1 and r["reenabled_after_safe_stop"] == r["safe_stops"]
    assert r["cycles"] == CYCLES
    times = r["exchange_us"]
    assert times["good"]["cycles"] + times["miss"]["cycles"] + times["recovery"]["cycles"] == CYCLES
    assert times["recovery"]["cycles"] > 0 and times["good"]["p50"] < times["good"]["max"]


def test_the_checker_catches_a_cycle_longer_than_its_budget() -> None:
    """With a margin below what a cycle costs, every cycle is reported: the timing invariant can fail."""
    r = soak(_args("sim", cycles=300, faults="loss=0.01", margin_us=-490.0), FaultSpec.parse("loss=0.01"))
    assert r["violation_count"] > 100
    assert "more than the receive timeout plus -490 us" in r["violations"][0]


def test_the_checker_catches_a_loss_that_never_happened(monkeypatch: pytest.MonkeyPatch) -> None:
    """A harness whose 'drop' does nothing must report violations: the invariants can fail."""
    from sim_slaves.ethercat import runner

    real = runner.handle_control

    def no_drop(chain: object, msg: dict[str, object]) -> dict[str, object]:
        if msg.get("cmd") == "drop":
            return {"ok": True}
        return real(chain, msg)  # type: ignore[arg-type]

    monkeypatch.setattr(runner, "handle_control", no_drop)
    r = soak(_args("sim", cycles=2000, faults="loss=0.02"), FaultSpec.parse("loss=0.02"))
    assert r["violation_count"] >= r["injected"]["loss"] > 0
    assert "reported fresh" in r["violations"][0]
    assert r["detected"].get("loss", 0) == 0


def test_soak_on_canopen_accounts_for_every_fault() -> None:
    """CANopen on the virtual bus: TPDO loss, node resets, a burst, SDO abort, EMCYs, heartbeat loss, bus-off."""
    pytest.importorskip("can")
    faults = "loss=0.01,power_cycles=2,bursts=1,sdo_aborts=1,emcys=2,heartbeats=1,bus_offs=1"
    cycles = max(1000, CYCLES // 3)  # a CAN cycle on the virtual bus costs ~2 ms: keep CI short
    r = soak(_args("canopen", axes=6, cycles=cycles, faults=faults, rate=0.0), FaultSpec.parse(faults))
    assert r["violation_count"] == 0, r["violations"]
    assert r["injected"] == r["detected"]
    assert (
        r["injected"]["emcy"] == 2 and r["injected"]["heartbeat"] == 1 and r["injected"]["power_cycle"] == 2
    )
    assert r["injected"]["bus_off"] == 1
    assert r["recovered_power_cycles"] >= 2  # heartbeat losses and bus-off are recovered the same way
    assert r["cycles"] == cycles


def test_faults_without_meaning_on_a_bus_are_refused() -> None:
    from fieldbus.runtime.soak import FaultSpecError

    with pytest.raises(FaultSpecError, match="emcys"):
        soak(_args("sim", cycles=300, faults="emcys=1"), FaultSpec.parse("emcys=1"))
