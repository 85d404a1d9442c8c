"""The observers carry BusStatus by deriving its fields from the dataclass (fieldbus.core.status_fields).

A field added to a BusStatus subclass (put in place of BusStatus for one run) reaches the recording,
the testing kit's trace, the ``--monitor`` snapshot and the DDS diagnostics values without any of
them naming it; and every field of the real BusStatus is carried or explicitly excluded by each.
The run is the in-process EtherCAT emulator (our own), on a virtual clock.
"""

from __future__ import annotations

import dataclasses
import importlib
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from fieldbus.core import status_fields as sf
from fieldbus.core.status_fields import Carry, check_covered, status_fields
from fieldbus.network import BusStatus
from fieldbus.operations import monitor
from fieldbus.recording import Recorder, load, ring
from fieldbus.testing import emulate
from fieldbus.testing import trace as trace_mod

pytestmark = pytest.mark.timeout(300)
IO16 = Path(__file__).resolve().parents[1] / "data" / "io16.yaml"


@dataclasses.dataclass(frozen=True)
class _Fault:
    """A nested dataclass in the status (as a typed ``fault: BusFault | None`` would be)."""

    slave: str
    code: int

    def __str__(self) -> str:
        return f"{self.slave}: 0x{self.code:04X}"


@dataclasses.dataclass
class _WithExtras(BusStatus):
    brake_hits: int = 0  # a new number
    torque_ns: int | None = None  # a new optional number
    brake_fault: _Fault | None = None  # a new nested dataclass


def _build_statuses_as(cls: type, monkeypatch: pytest.MonkeyPatch) -> None:
    """``cls`` in place of BusStatus where the network builds its statuses (fieldbus.network; its bus
    cycle module once the network is a façade)."""
    patched = 0
    for name in ("fieldbus.network", "fieldbus.cycle.buscycle"):
        try:
            module = importlib.import_module(name)
        except ImportError:
            continue
        if isinstance(getattr(module, "BusStatus", None), type):
            monkeypatch.setattr(module, "BusStatus", cls)
            patched += 1
    assert patched


def _net(tmp_path: Path) -> Path:
    f = tmp_path / "io.yaml"
    f.write_text(
        "cycle_time_us: 1000\nbuses:\n  - {name: io, type: ethercat, interface: sim, "
        f"slaves: [{{name: 'io{{i}}', map: '{IO16}', count: 2}}]}}\n"
    )
    return f


def test_fields_are_carried_by_their_type_a_nested_dataclass_as_text() -> None:
    got = {f.name: f for f in status_fields(_WithExtras)}
    assert got["name"].carry is Carry.CONSTANT and got["expected_wkc"].carry is Carry.CONSTANT
    assert got["fresh"].carry is Carry.PER_SLAVE
    assert got["verdict"].carry is Carry.NUMBER and not got["verdict"].flag  # an IntEnum
    assert got["safe_stop"].carry is Carry.NUMBER and got["safe_stop"].flag
    assert got["dc_time_ns"].carry is Carry.NUMBER and got["dc_time_ns"].optional
    assert got["recovery_error"].carry is Carry.TEXT
    assert got["brake_hits"].carry is Carry.NUMBER and got["torque_ns"].optional
    assert got["brake_fault"].carry is Carry.TEXT and got["brake_fault"].optional
    assert sf.plain(_Fault("j1", 0x7300)) == "j1: 0x7300" and sf.plain(BusStatus.verdict) == "OK"


def test_an_annotation_that_cannot_be_resolved_is_text_and_the_others_still_resolve() -> None:
    ns: dict[str, Any] = {}
    exec(  # a type named only for type checking: get_type_hints cannot resolve it
        "from __future__ import annotations\nimport dataclasses\n"
        "@dataclasses.dataclass\nclass S:\n    hits: int = 0\n    fault: NotImported | None = None\n",
        ns,
    )
    got = {f.name: f.carry for f in status_fields(ns["S"])}
    assert got == {"hits": Carry.NUMBER, "fault": Carry.TEXT}


def test_a_field_added_to_bus_status_flows_to_recording_trace_monitor_and_dds(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from fieldbus.dds.bus_values import bus_values  # needs cyclonedds (fieldbus[dds])

    _build_statuses_as(_WithExtras, monkeypatch)
    path = tmp_path / "run.mcap"
    with emulate(_net(tmp_path)) as emu:
        op = emu.op
        st = op.result.buses[0]
        assert isinstance(st, _WithExtras)
        rec = Recorder(op, path, block_cycles=8, ring_blocks=32)
        first = emu.trace.mark()

        def step(k: int) -> None:
            st.brake_hits = 3 * k
            st.torque_ns = None if k % 2 else k
            if k >= first + 10:  # a new, equal fault object every cycle; another fault from +20 on
                st.brake_fault = _Fault("io1", 0x7300 if k < first + 20 else 0x2310)
            op.exchange()

        emu.run(step, 40)
        snap = monitor.Monitor(op).snapshot()["buses"][0]
        values = {kv.key: kv.value for kv in bus_values(st, op.buses[0].counters())}
        rec.close()
        trace = emu.trace
        k = np.arange(first, first + 40)
        # the trace: a number column per new number, the text field's changes
        assert (trace.status("io", "brake_hits")[first:] == 3 * k).all()
        assert (trace.status("io", "torque_ns")[first:] == np.where(k % 2, sf.NO_VALUE, k)).all()
        assert trace.texts("io", "brake_fault") == [(first + 10, "io1: 0x7300"), (first + 20, "io1: 0x2310")]
        assert "io.brake_hits" in trace.arrays()
    # the monitor and the DDS diagnostics: the last values, by name
    assert (snap["brake_hits"], snap["torque_ns"], snap["brake_fault"]) == (3 * k[-1], None, "io1: 0x2310")
    assert (values["brake_hits"], values["torque_ns"], values["brake_fault"]) == (
        str(3 * k[-1]),
        "",
        "io1: 0x2310",
    )
    # the recording: the numbers as columns of the bus rows, the text as an event of its name
    r = load(path)
    bus = r.buses["io"]
    c = bus["cycle"].astype(np.int64)
    rows = c >= first
    assert rows.sum() == 40 and (bus["brake_hits"][rows] == 3 * c[rows]).all()
    assert (bus["torque_ns"][rows] == np.where(c[rows] % 2, sf.NO_VALUE, c[rows])).all()
    faults = [e for e in r.events if e["kind"] == "brake_fault"]
    assert [(e["cycle"], e["bus"], e["detail"]) for e in faults] == [
        (first + 10, "io", "io1: 0x7300"),
        (first + 20, "io", "io1: 0x2310"),
    ]  # a new object equal to the last is no change


def test_every_bus_status_field_is_carried_or_excluded_by_each_observer(tmp_path: Path) -> None:
    from fieldbus.dds import bus_values as dds_values

    path = tmp_path / "run.mcap"
    with emulate(_net(tmp_path)) as emu:
        op = emu.op
        rec = Recorder(op, path, block_cycles=8, ring_blocks=32)
        emu.cycles(20)
        snap = monitor.Monitor(op).snapshot()["buses"][0]
        dds = {kv.key for kv in dds_values.bus_values(op.result.buses[0], op.buses[0].counters())}
        rec.close()
        tr = emu.trace
        traced = {*tr.status_names, *tr.text_names, "verdict", "wkc"}
    recorded = {*load(path).buses["io"].dtype.names, *rec.ring.columns.texts}  # texts: events of their name
    carried = {
        "fieldbus.recording.ring": (recorded, ring.EXCLUDED),
        "fieldbus.testing.trace": (traced, trace_mod.EXCLUDED),
        "fieldbus.operations.monitor": (set(snap), monitor.EXCLUDED),
        "fieldbus.dds.bus_values": (dds, dds_values.EXCLUDED),
    }
    names = {f.name for f in dataclasses.fields(BusStatus)}
    for observer, (have, excluded) in carried.items():
        assert check_covered(BusStatus, have, excluded, observer) == []
        assert set(excluded) <= names, (
            f"{observer}.EXCLUDED names no BusStatus field: {set(excluded) - names}"
        )
        assert not set(excluded) & have, f"{observer} both carries and excludes {set(excluded) & have}"
    # and the /cycle row carries CycleResult's numbers, or names where the rest is
    from fieldbus.network import CycleResult

    cycle_cols = set(load(path).cycles.dtype.names)
    assert {"fresh", "safe_stop", "exchange_ns"} <= cycle_cols
    assert check_covered(CycleResult, cycle_cols, ring.CYCLE_EXCLUDED, "the /cycle row") == []
    # the check can fail: a hand-kept list (the recording's before) misses a field added to the class
    old = {"ran", "verdict", "wkc", "consecutive_misses", "safe_stop", "recovering", "recoveries", "fresh"}
    missing = check_covered(_WithExtras, old | {"dc_time_ns", "dc_sync_error_ns"}, ring.EXCLUDED, "recording")
    assert "_WithExtras.brake_hits is neither carried by recording nor named in its EXCLUDED" in missing
    assert any(m.startswith("_WithExtras.brake_fault ") for m in missing)


def test_the_cycles_events_are_recorded_with_every_field_of_their_dataclass() -> None:
    from fieldbus.core.drivefault import DriveFault
    from fieldbus.core.output_rules import OutputClamp, Reason
    from fieldbus.recording.writer import EVENT_EXCLUDED, EVENT_RENAMED

    @dataclasses.dataclass(frozen=True)
    class _MotorFault(DriveFault):
        temperature_c: float = 0.0  # a field a subclass adds

    got = sf.event_fields(
        _MotorFault(7, "legs", 1, "m1", 0x7300, 81.5, slave_axis=1), EVENT_RENAMED, EVENT_EXCLUDED
    )
    assert got == {
        "group": "legs", "axis": 1, "slave": "m1", "code": 0x7300, "slave_axis": 1, "history": None,
        "temperature_c": 81.5,
    }  # fmt: skip
    clamp = OutputClamp(5, "arm", 2, "target_position", Reason.NAN, float("nan"), 0.1)
    got = sf.event_fields(clamp, EVENT_RENAMED, EVENT_EXCLUDED)
    asked = got.pop("asked")
    assert isinstance(asked, float) and math.isnan(asked)  # what the controller wrote, as it was
    assert got == {"group": "arm", "axis": 2, "channel": "target_position", "name": "NAN", "sent": 0.1}
