"""Raw-CAN motor faults as cycle events: a Damiao error code and an ODrive axis error injected in the
emulators arrive in ``CycleResult.events`` with axis, code and name, once per onset, and in the recording.

The emulators are our own code (sim_slaves); the codes and names they are judged by are the published
ones (Damiao error nibble 0xE overload; ODrive MOTOR_OVER_TEMP 0x2000), written out here.
"""

from __future__ import annotations

import itertools
import os
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest

can = pytest.importorskip("can")

from fieldbus import PDO_MAPS, open_network  # noqa: E402
from fieldbus.core.drivefault import DriveFault  # noqa: E402
from fieldbus.core.pdo import load_drive_map  # noqa: E402
from sim_slaves.damiao import DamiaoSimulator  # noqa: E402
from sim_slaves.odrive import OdriveSimulator  # noqa: E402

pytestmark = pytest.mark.timeout(120)
NODES = (1, 2, 3)
WITHIN = 5  # cycles an injected fault may take to reach the events (the ODrive tells in its heartbeat)
_channels = itertools.count()


class VirtualClock:
    """The emulators' seconds. ``live``: they pass with the wall clock (the bring-up: an ODrive's heartbeats
    keep coming however late the master opens its bus); else only when the test says so (the cycles: a
    loaded machine never trips a motor's CAN timeout)."""

    def __init__(self) -> None:
        self.t = 0.0
        self.live = True
        self._t0 = time.monotonic()

    def __call__(self) -> float:
        return time.monotonic() - self._t0 if self.live else self.t

    def freeze(self) -> None:
        """From now on, time passes only by ``t +=``."""
        self.t = self()
        self.live = False


def _net(tmp_path: Path, bus: str, prefix: str, map_name: str) -> tuple[Path, str]:
    channel = f"fb-ev-{os.getpid()}-{next(_channels)}"
    net = tmp_path / "net.yaml"
    net.write_text(
        "cycle_time_us: 1000\nreceive_timeout_us: 20000\nsafe_stop_after: 50\nbuses:\n"
        f"  - {{name: {bus}, type: rawcan, interface: {channel}, can_interface: virtual,\n"
        f"     slaves: [{{name: '{prefix}{{i}}', map: {Path(PDO_MAPS) / map_name}, node_id: 1, "
        f"count: {len(NODES)}}}]}}\n"
    )
    return net, channel


def _faults(events: list[Any]) -> list[DriveFault]:
    return [e for e in events if isinstance(e, DriveFault)]


@contextmanager
def _damiao_arm(tmp_path: Path) -> Iterator[tuple[DamiaoSimulator, Any, Any]]:
    """Damiao motors on a virtual bus, brought up; their clock frozen (the motors' 50 ms TIMEOUT runs
    on it: never reached here). Yields (emulator, network, operational)."""
    net, channel = _net(tmp_path, "arm", "j", "damiao_dm_j4310.yaml")
    drive = load_drive_map(Path(PDO_MAPS) / "damiao_dm_j4310.yaml")
    clock = VirtualClock()
    with (
        can.Bus(interface="virtual", channel=channel) as sim_bus,
        DamiaoSimulator(sim_bus, [(drive, n) for n in NODES], dt_s=0.001, clock=clock) as sim,
        open_network(net) as network,
    ):
        op = network.bring_up()
        clock.freeze()
        yield sim, network, op


def test_damiao_error_code_is_one_named_event_and_recorded(tmp_path: Path) -> None:
    from fieldbus.recording import load

    with _damiao_arm(tmp_path) as (sim, network, op):
        rec = op.record(tmp_path / "run.mcap")
        for _ in range(10):
            assert _faults(op.exchange().events) == []
        sim.inject_error(3, 0xE)  # overload on node 3 = j2, row 2
        seen: list[tuple[int, DriveFault]] = []
        for k in range(WITHIN + 40):  # the code stays set: one event at its onset, none after
            res = op.exchange()
            seen += [(k, f) for f in _faults(res.events)]
        assert len(seen) == 1, seen
        k, ev = seen[0]
        assert k < WITHIN
        assert (ev.group, ev.axis, ev.slave, ev.code, ev.name) == ("arm", 2, "j2", 0xE, "overload")
        assert str(ev) == "j2 (arm[2]): motor fault 0xE overload"
        # cleared, then a new onset is a new event
        assert network.backends[0].clear_errors() == []
        for _ in range(5):
            op.exchange()
        sim.inject_error(1, 0x8)
        again = [f for _ in range(WITHIN) for f in _faults(op.exchange().events)]
        assert [(f.slave, f.code, f.name) for f in again] == [("j0", 0x8, "over-voltage")]
        rec.close()
    recorded = [e for e in load(tmp_path / "run.mcap").events if e["kind"] == "drive_fault"]
    assert [(e["slave"], e["code"], e["name"]) for e in recorded] == [
        ("j2", 0xE, "overload"),
        ("j0", 0x8, "over-voltage"),
    ]


def test_damiao_unnamed_code_is_named_by_number_at_each_onset(tmp_path: Path) -> None:
    """A code the map does not name (0x5) is a fault named by its number; the same code again after a
    clear is a new onset with the same name."""
    with _damiao_arm(tmp_path) as (sim, network, op):
        got = []
        for _ in range(2):
            sim.inject_error(2, 0x5)
            got += [f for _ in range(WITHIN + 10) for f in _faults(op.exchange().events)]
            assert network.backends[0].clear_errors() == []
            assert [f for _ in range(5) for f in _faults(op.exchange().events)] == []
    assert [(f.slave, f.code, f.name) for f in got] == [("j1", 0x5, "unknown error 0x5")] * 2


@pytest.mark.parametrize("map_name", ["odrive_s1.yaml", "odrive_3_6.yaml"])
def test_odrive_axis_error_is_one_named_event(tmp_path: Path, map_name: str) -> None:
    net, channel = _net(tmp_path, "legs", "a", map_name)
    drive = load_drive_map(Path(PDO_MAPS) / map_name)
    clock = VirtualClock()
    with (
        can.Bus(interface="virtual", channel=channel) as sim_bus,
        OdriveSimulator(sim_bus, [(drive, n) for n in NODES], dt_s=0.001, clock=clock, heartbeat_ms=2) as sim,
        open_network(net) as network,
    ):
        op = network.bring_up()
        clock.freeze()
        for _ in range(10):
            clock.t += 0.001
            assert _faults(op.exchange().events) == []
        bit, name = (
            (0x00040000, "OVER_TEMP") if map_name == "odrive_3_6.yaml" else (0x2000, "MOTOR_OVER_TEMP")
        )
        sim.inject_error(2, bit)  # node 2 = a1, row 1
        seen: list[tuple[int, DriveFault]] = []
        for k in range(WITHIN + 40):  # heartbeats keep repeating the error: one event at its onset
            clock.t += 0.001
            seen += [(k, f) for f in _faults(op.exchange().events)]
        assert len(seen) == 1, seen
        k, ev = seen[0]
        assert k < WITHIN
        assert (ev.group, ev.axis, ev.slave, ev.code, ev.name) == ("legs", 1, "a1", bit, name)
