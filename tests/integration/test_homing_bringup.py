"""A drive map's ``homing:`` section, end to end: bring-up writes it, ``Homing`` runs it, then CSP.

On the sim backend (the in-process EtherCAT emulator) on a virtual clock,
1 ms per exchange; and on the CANopen emulator over python-can's virtual bus.
The emulated drives' home switches sit at -1 rad and +1 rad of the motor shaft
from where they powered on, index pulses every revolution from -1 rad
(``sim_slaves.drive402``): method 17 homes at the negative switch, 34 at the
next index pulse in the positive direction; either way the position actual
there reads the map's home offset.
"""

from __future__ import annotations

import itertools
import json
import time
from pathlib import Path

import numpy as np
import pytest

import fieldbus
from fieldbus import Cia402Controller, Goal, Homing, Mode
from fieldbus.core.cia402 import HomingPhase
from fieldbus.testing import VirtualClock

DEMO_MAP = Path(fieldbus.__file__).resolve().parent / "data" / "demo_joint.yaml"
RAD_PER_COUNT = 4.79369e-5  # demo_joint.yaml, inputs
HIP_OFFSET, KNEE_OFFSET = 10_000, -20_000  # counts: where the home point reads
_channels = itertools.count()


def _maps(tmp_path: Path) -> tuple[Path, Path]:
    base = DEMO_MAP.read_text()
    hip, knee = tmp_path / "hip.yaml", tmp_path / "knee.yaml"
    hip.write_text(
        base.replace("name: demo_joint", "name: hip")
        + f"homing:\n  method: 17\n  offset: {HIP_OFFSET}\n  speeds: {{switch: 100000, zero: 10000}}\n"
        "  acceleration: 1000000\n  timeout_ms: 2000\n"
    )
    knee.write_text(
        base.replace("name: demo_joint", "name: knee")
        + f"homing: {{method: 34, offset: {KNEE_OFFSET}, speeds: {{switch: 100000, zero: 200000}},"
        " timeout_ms: 3000}\n"
    )
    return hip, knee


def _net(tmp_path: Path, bus: str, can: bool = False) -> Path:
    hip, knee = (json.dumps(str(p)) for p in _maps(tmp_path))
    ids = (", node_id: 1", ", node_id: 2") if can else ("", "")
    f = tmp_path / "net.yaml"
    f.write_text(
        f"cycle_time_us: 1000\nreceive_timeout_us: {50000 if can else 5000}\nsafe_stop_after: 10\nbuses:\n"
        f"  - {{{bus}, slaves: [{{name: hip, map: {hip}{ids[0]}}},"
        f" {{name: 'knee{{i}}', map: {knee}{ids[1]}, count: 2}}]}}\n"
    )
    return f


def _home_then_csp(op: fieldbus.Operational, tick: object) -> list[int]:
    """Hip first, then knee0, then knee1 (the declared order), then 300 cycles of CSP from home.

    Returns the cycle at which each of hip, knee0, knee1 was homed."""
    names = ("arm.hip", "arm.knee0")
    imgs = [op[g] for g in names]
    ctrls = [Cia402Controller(img.n_axes, mode=Mode.CSP) for img in imgs]
    homings = [
        Homing.from_maps(c, [s.map for s in op.groups[g].slaves], op.cycle_time_us)
        for c, g in zip(ctrls, names, strict=True)
    ]
    assert list(homings[0].timeout_cycles) == [2000] and list(homings[1].timeout_cycles) == [3000] * 2
    for c in ctrls:
        c.set_goal(Goal.ENABLE)
    homings[0].start()
    knees_started = False
    homed_at = [-1, -1, -1]
    misses = 0
    for k in range(6000):
        tick()  # type: ignore[operator]
        if not op.exchange().fresh:  # a late reply (the virtual CAN bus is threads): a held cycle
            misses += 1
            continue
        for c, h, img in zip(ctrls, homings, imgs, strict=True):
            c.step_image(img)
            h.step(img.inputs["statusword"], img.outputs["controlword"])
        if not knees_started and homings[0].done:
            homings[1].start(order=[[0], [1]])
            knees_started = True
        phases = [homings[0].phase[0], *homings[1].phase]
        for i, ph in enumerate(phases):
            if ph == HomingPhase.DONE and homed_at[i] < 0:
                homed_at[i] = k
        if knees_started and homings[1].done and all(c.all_reached for c in ctrls):
            break
    assert [homings[0].phase[0], *homings[1].phase] == [HomingPhase.DONE] * 3
    for img in imgs:
        assert np.all(img.inputs["modes_of_operation_display"] == Mode.CSP)
    hip_pos = float(imgs[0].inputs["position_actual_value"][0])
    knee_pos = imgs[1].inputs["position_actual_value"]
    # still at the home point (it stopped within a few cycles of it), which reads the offset
    assert abs(hip_pos - HIP_OFFSET * RAD_PER_COUNT) < 0.05, hip_pos
    assert np.all(np.abs(knee_pos - KNEE_OFFSET * RAD_PER_COUNT) < 0.05), knee_pos
    # CSP from home: the bumpless seed starts at the position actual, the user adds 0.4 rad in 400 cycles
    start = [img.inputs["position_actual_value"].copy() for img in imgs]
    moved_cycles = 0
    while moved_cycles < 400:
        tick()  # type: ignore[operator]
        if not op.exchange().fresh:
            misses += 1
            continue
        moved_cycles += 1
        for c, img in zip(ctrls, imgs, strict=True):
            c.step_image(img)
            t = img.outputs["target_position"]
            t += 0.001  # 1 mrad per cycle: 0.4 rad in 400 cycles
    for s, img in zip(start, imgs, strict=True):
        moved = img.inputs["position_actual_value"] - s
        assert np.all(np.abs(moved - 0.4) < 0.05), moved
    assert misses < 100, misses  # none on the sim backend's virtual clock; a few late CAN replies
    return homed_at


def _read(op: fieldbus.Operational, tick: object, slave: str, index: int, sub: int) -> bytes:
    """An SDO upload served by the cycle (the caller runs the cycle: submit, then exchange until done)."""
    fut = op.submit_sdo_read("arm", slave, index, sub)
    for _ in range(2000):
        if fut.done():
            break
        tick()  # type: ignore[operator]
        op.exchange()
    data = fut.result(timeout=0)
    assert data is not None
    return data


def _check_order(homed_at: list[int]) -> None:
    hip, knee0, knee1 = homed_at
    assert 0 < hip < knee0 < knee1, homed_at
    # the hip searched its switch (1 rad at 100000 counts/s ≈ 4.8 rad/s: some 200 cycles)
    assert hip > 150


def test_homing_section_on_the_sim_backend_homes_in_order_then_runs_csp(tmp_path: Path) -> None:
    clock = VirtualClock()
    net = fieldbus.open_network(
        _net(tmp_path, "name: arm, type: ethercat, interface: sim0"), backend="sim", clock=clock
    )
    try:
        op = net.bring_up()
        hip = op.groups["arm.hip"].slaves[0].map
        assert hip.homing is not None and hip.homing.method == 17
        # bring-up wrote the section: the drive holds it
        tick = lambda: clock.advance(1_000_000)  # noqa: E731
        assert _read(op, tick, "hip", 0x6098, 0) == b"\x11"
        assert _read(op, tick, "knee1", 0x6099, 2) == (200000).to_bytes(4, "little")
        assert int.from_bytes(_read(op, tick, "knee0", 0x607C, 0), "little", signed=True) == KNEE_OFFSET
        _check_order(_home_then_csp(op, tick))
    finally:
        net.close()


def test_homing_section_over_canopen_on_the_canopen_emulator(tmp_path: Path) -> None:
    can = pytest.importorskip("can")
    from sim_slaves.canopen import CanopenSimulator

    channel = f"fb-homing-{next(_channels)}-{time.monotonic_ns()}"
    hip_map, knee_map = (fieldbus.load_drive_map(p) for p in _maps(tmp_path))
    net_file = _net(tmp_path, f"name: arm, type: canopen, interface: {channel}, can_interface: virtual", True)
    with (
        can.Bus(interface="virtual", channel=channel) as bus,
        CanopenSimulator(bus, [(hip_map, 1), (knee_map, 2), (knee_map, 3)], dt_s=1e-3) as sim,
        fieldbus.open_network(net_file) as net,
    ):
        op = net.bring_up()
        assert _read(op, lambda: None, "hip", 0x6098, 0) == b"\x11"
        assert sim.node(3).od.get_value(0x6099, 2) == 200000  # written by bring-up over CANopen
        _check_order(_home_then_csp(op, lambda: None))
    assert not sim.errors
