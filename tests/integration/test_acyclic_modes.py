"""Mode switching and homing on a drive map without 0x6060/0x6061 in its PDOs: the mode objects go by SDO.

The demo joint's map with modes_of_operation and its display removed from the PDOs (a ``homing:``
section, method 37: home on the current position, added). ``AcyclicModes`` carries the mode request as
an SDO download of 0x6060 and reads 0x6061 back by SDO, queued on the in-OP acyclic channel; the
controller waits for the display as it waits for the PDO one. On the in-process EtherCAT emulator in
virtual time (1 ms per exchange); judged by the emulated drives' own state (their mode, the value in
their object dictionary), which the library's SDO codec wrote.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import yaml

import fieldbus
from fieldbus.commands.demo import DEMO_MAP
from fieldbus.core.acyclic_modes import AcyclicModes
from fieldbus.core.cia402 import Cia402Controller, Goal, Homing, HomingPhase, Mode, State402
from fieldbus.core.profile import ProfileMove, ProfilePhase
from fieldbus.platform.clock import VirtualClock

RECEIVE_TIMEOUT_NS = 5_000_000


class _Tick:
    """One cycle time passes on the virtual clock after every exchange()."""

    def __init__(self, clock: VirtualClock) -> None:
        self.clock = clock

    def capture(self, res: fieldbus.CycleResult, t0_ns: int) -> None:
        self.clock.advance(1_000_000)

    def note_events(self, events: list[Any]) -> None:
        pass

    def close(self) -> None:
        pass


def _map_without_modes(tmp_path: Path) -> Path:
    doc = yaml.safe_load(Path(DEMO_MAP).read_text())
    for section in ("rpdo", "tpdo"):
        for pdo in doc[section]:
            pdo["channels"] = [c for c in pdo["channels"] if c["index"] not in (0x6060, 0x6061)]
    doc["name"] = "joint_no_modes"
    doc["homing"] = {"method": 37, "offset": 0, "timeout_ms": 2000}
    f = tmp_path / "joint_no_modes.yaml"
    f.write_text(yaml.safe_dump(doc, sort_keys=False))
    return f


def _open(tmp_path: Path) -> tuple[fieldbus.Network, VirtualClock]:
    f = tmp_path / "net.yaml"
    m = json.dumps(str(_map_without_modes(tmp_path)))
    f.write_text(
        "cycle_time_us: 1000\nreceive_timeout_us: 5000\nbuses:\n"
        f"  - {{name: arm, type: ethercat, interface: sim0, slaves: [{{name: 'j{{i}}', map: {m}, count: 2}}]}}\n"
    )
    clock = VirtualClock()
    return fieldbus.open_network(f, backend="sim", clock=clock), clock


def test_home_and_switch_modes_by_sdo_when_the_mode_objects_are_not_in_the_pdos(tmp_path: Path) -> None:
    net, clock = _open(tmp_path)
    try:
        op = net.bring_up()
        tick = _Tick(clock)
        op.add_observer(tick)
        img = op["arm"]
        assert "modes_of_operation" not in img.outputs.names  # the premise: no mode channel at all
        drives = [s.app for s in net.backend("arm").chain.slaves]  # type: ignore[attr-defined]
        ctrl = Cia402Controller(2, mode=Mode.CSP)
        modes = AcyclicModes.for_group(op, "arm")
        ctrl.set_goal(Goal.ENABLE)
        spans: list[int] = []

        def cycle() -> None:
            t0 = clock.now_ns()
            res = op.exchange()
            spans.append(clock.now_ns() - t0)
            assert res.fresh  # no cycle held or lost while the SDOs run beside it
            ctrl.step_image(img, modes=modes)

        def run_until(done: Any, limit: int = 2000) -> int:
            for k in range(limit):
                cycle()
                if done():
                    return k + 1
            raise AssertionError(f"not done in {limit} cycles: {ctrl.state}, display {modes.display}")

        run_until(lambda: ctrl.all_reached)
        assert [d.state for d in drives] == [State402.OPERATION_ENABLED] * 2
        assert list(modes.display) == [Mode.CSP] * 2

        homing = Homing.from_maps(ctrl, [s.map for s in op.groups["arm"].slaves], 1000)
        homing.start()

        drive_modes: set[tuple[int, ...]] = set()

        def homed() -> bool:
            homing.step(img.inputs["statusword"], img.outputs["controlword"])
            drive_modes.add(tuple(int(d.mode_display) for d in drives))
            return homing.done and ctrl.all_reached

        run_until(homed)
        assert list(homing.phase) == [HomingPhase.DONE] * 2
        assert list(modes.display) == [Mode.CSP] * 2  # back to CSP, by SDO too
        assert (Mode.HOMING, Mode.HOMING) in drive_modes  # the drives themselves were in HM
        assert [int(d.mode_display) for d in drives] == [Mode.CSP] * 2

        for mode in (Mode.CSV, Mode.CSP):
            ctrl.request_mode(mode)
            took = run_until(lambda m=mode: ctrl.all_reached and bool((modes.display == m).all()))
            assert took >= 2  # a download, then an upload: spread over cycles, one step each
            assert [int(d.mode_display) for d in drives] == [int(mode)] * 2  # the drives' own mode
        # profile position (PP, mode 1) through the same SDO path: a 0.5 rad move, then back to CSP
        moves = ProfileMove(ctrl)
        start = img.inputs["position_actual_value"].copy()
        moves.move_to(start + 0.5)
        pp_modes: set[tuple[int, ...]] = set()

        def moved() -> bool:
            moves.step_image(img)
            pp_modes.add(tuple(int(d.mode_display) for d in drives))
            return moves.done

        run_until(moved, limit=5000)
        assert (
            list(moves.phase) == [ProfilePhase.DONE] * 2
            and (Mode.PROFILE_POSITION, Mode.PROFILE_POSITION) in pp_modes
        )
        assert np.allclose(img.inputs["position_actual_value"], start + 0.5, atol=0.01)
        ctrl.request_mode(Mode.CSP)
        run_until(lambda: ctrl.all_reached and bool((modes.display == Mode.CSP).all()))
        # every switch was one SDO download of 0x6060 per axis: CSP, HM, CSP, CSV, CSP, PP, CSP
        assert list(modes.writes) == [7, 7]
        assert (modes.reads >= 7).all()
        # the cycle never waited for an SDO: each exchange spans no virtual time at all
        assert max(spans) <= RECEIVE_TIMEOUT_NS
        assert np.all(img.inputs["statusword"] & 0x0008 == 0)
    finally:
        net.close()
