"""The backend contract is written on the base class: every optional capability has a default there.

Callers read a capability (counters, bus-off, slave states, NMT states,
emergencies, ESC error watch, motor faults and their events, the recovery step,
the stop/close verbs) as a method or attribute of :class:`Backend`, never by
probing a backend for it by name: the probe scan below fails when one comes
back anywhere in ``fieldbus/``, and is shown to catch the probes it replaced.
"""

from __future__ import annotations

import re
from pathlib import Path

from fieldbus.backends.base import COUNTERS, Backend
from fieldbus.core.network import load_network

ROOT = Path(__file__).resolve().parents[2]
PACKAGE = ROOT / "fieldbus"

CAPABILITIES = (
    *COUNTERS,
    "slave_state",
    "take_motor_events",
    "last_emergency",
    "last_emergency_name",
    "emergencies",
    "error_watch",
    "node_ids",
    "nmt_state",
    "faults",
    "recover_step",
    "recovering",
    "stop",
    "close",
)
# getattr/hasattr on something named like a backend (b, backend, x.backend, backends[i]) ...
_ON_BACKEND = re.compile(r"\b(?:getattr|hasattr)\(\s*(?:[\w\]\[]+\.)*(?:backend|backends\[[^\]]*\]|b)\s*,")
# ... or on anything, with a capability's name spelled out
_BY_NAME = re.compile(r"\b(?:getattr|hasattr)\([^,()]+,\s*[\"'](?:" + "|".join(CAPABILITIES) + r")[\"']")


def probes(source: str) -> list[str]:
    """The lines of ``source`` that probe a backend for a capability by name."""
    return [line.strip() for line in source.splitlines() if _ON_BACKEND.search(line) or _BY_NAME.search(line)]


def test_no_capability_probe_in_fieldbus() -> None:
    found = []
    files = sorted(PACKAGE.rglob("*.py"))
    assert len(files) > 80  # the whole package was read
    for path in files:
        found += [f"{path.relative_to(ROOT)}: {line}" for line in probes(path.read_text())]
    assert found == []


def test_the_scan_catches_the_probes_it_replaced() -> None:
    replaced = [
        "out = {name: int(getattr(self.backend, name, 0) or 0) for name in COUNTERS}",
        'state_of = getattr(self.backend, "slave_state", None)',
        "getattr(b, verb)()",
        'int(getattr(b, "bus_off", 0)) if hasattr(b, "bus_off") else None for b in net.backends',
        'getattr(b, "take_motor_events", None) for b in net.backends',
        'emcy_of = getattr(b, "last_emergency", None)',
        'if isinstance(emcy_of, dict) and hasattr(b, "node_ids")',
        'before = len(getattr(backend, "emergencies", []))',
        'nmt_src = getattr(b, "nmt_state", None)',
        'watch = getattr(bv.backend, "error_watch", None)',
        'report["motor_faults"] = [str(f) for f in getattr(net.backends[0], "faults", ())]',
        'watch = getattr(view.backend, "error_watch", None)',
    ]
    assert [probes(line) for line in replaced] == [[line] for line in replaced]
    # and what is no probe is left alone: a clock's capability, an argparse namespace, a message field
    fine = [
        'if clock is not None and hasattr(clock, "now_ns") and hasattr(clock, "sleep"):',
        'if getattr(args, "record", None):',
        "values = getattr(cmd, field)",
    ]
    assert [probes(line) for line in fine] == [[] for _ in fine]


class Minimal(Backend):
    """A backend with only the abstract verbs: everything optional comes from the base class."""

    kind = "minimal"

    def open(self) -> None:
        pass

    def configure(self) -> None:
        pass

    def safe_op(self) -> None:
        pass

    def op(self) -> None:
        pass

    def send(self) -> None:
        pass

    def receive(self) -> int | None:
        return None

    def stop(self) -> None:
        pass

    def close(self) -> None:
        pass


def _minimal() -> Minimal:
    net = load_network(ROOT / "examples" / "demo_network.yaml")
    return Minimal(net.buses[0])


def test_a_minimal_backend_gets_every_default() -> None:
    b = _minimal()
    assert b.counters() == dict.fromkeys(COUNTERS, 0)
    assert [b.slave_state(i) for i in range(b.n_slaves)] == ["-"] * b.n_slaves
    assert [b.last_emergency_name(i) for i in range(b.n_slaves)] == [None] * b.n_slaves
    assert b.take_motor_events(7) == ()
    assert tuple(b.emergencies) == () and tuple(b.faults) == ()
    assert b.nmt_state is None and b.error_watch is None
    assert b.recover_step() is True and not b.recovering  # no recovery: nothing to do
    assert b.diag_step() == [] and b.arrived() is None and b.dc_correction_ns() == 0


def test_a_backend_that_has_a_capability_overrides_its_default() -> None:
    class Counting(Minimal):
        def slave_state(self, i: int) -> str:
            return "OP"

    b = Counting(_minimal().bus)
    b.tx_errors = 3
    b.bus_off = 1
    assert b.counters()["tx_errors"] == 3 and b.counters()["bus_off"] == 1
    assert b.slave_state(0) == "OP"
    assert Minimal.tx_errors == 0  # the default on the class is untouched
