"""The emulated drive's home point does not depend on how long the master leaves between frames.

Over veth the EtherCAT emulator steps its drives by the time between two frames (up to 0.1 s on a
loaded machine). A drive searching its home switch or index pulse at 4.8 rad/s used to look for it
only once per step, so a 0.1 s step ran up to 0.48 rad past the home point before the search
stopped: after homing the joint stood 0.2-0.5 rad from where the home offset (0x607C) puts it
(issue 25's veth day test). A real drive watches the switch in its own loop; the emulator now looks
at least every ``HOMING_CHECK_S`` of the drive's time. Scalar drive and bank alike; our own emulator
only (the independent check over the wire is tests/integration/test_cia402_day_veth.py).
"""

from __future__ import annotations

import pytest

from sim_slaves.drive402 import (
    HOMING_CHECK_S,
    Cia402Drive,
    DictObjectStore,
    DriveParams,
    Obj,
    default_objects,
)
from sim_slaves.drive_bank import DriveBank

SEARCH = 100_000  # switch search speed 0x6099:01 [counts/s] (~4.8 rad/s on the default 17-bit encoder)
# (method, home offset 0x607C [counts], zero search speed 0x6099:02 [counts/s]) as the veth day's hips/knees
CASES = ((17, 10_000, 10_000), (34, -20_000, 200_000))
RUN_S = 2.0  # long enough for every search and stop


def _od(p: DriveParams, method: int, offset: int, zero_speed: int) -> DictObjectStore:
    od = DictObjectStore(default_objects(p))
    od.values[(Obj.MODES_OF_OPERATION, 0)] = 6
    od.values[(0x6098, 0)] = method
    od.values[(0x607C, 0)] = offset
    od.values[(0x6099, 1)] = SEARCH
    od.values[(0x6099, 2)] = zero_speed
    return od


def _cw(k: int) -> int:
    return 0x06 if k < 3 else 0x07 if k < 6 else 0x0F if k < 10 else 0x1F  # enable, then bit 4 at step 10


def _home(method: int, offset: int, zero_speed: int, dt: float, *, bank: bool) -> tuple[int, int]:
    """Home one drive in steps of ``dt`` [s]; its statusword and position actual value [counts] after RUN_S."""
    p = DriveParams()
    od = _od(p, method, offset, zero_speed)
    b = DriveBank([p]) if bank else None
    d = Cia402Drive(p)
    for k in range(round(RUN_S / dt)):
        od.values[(Obj.CONTROLWORD, 0)] = _cw(k)
        if b is None:
            d.step(od, dt)
        else:
            b.load_inputs(0, od)
            b.step(0, 1, dt)
            b.store_outputs(0, od)
    return int(od.values[(Obj.STATUSWORD, 0)]), int(od.values[(Obj.POSITION_ACTUAL, 0)])


@pytest.mark.parametrize("bank", [False, True], ids=["scalar", "bank"])
@pytest.mark.parametrize(("method", "offset", "zero_speed"), CASES)
def test_long_steps_stop_where_short_steps_do(method: int, offset: int, zero_speed: int, bank: bool) -> None:
    sw_ref, ref = _home(method, offset, zero_speed, 1e-3, bank=bank)
    assert sw_ref & 0x3400 == 0x1400, hex(sw_ref)  # attained, target reached
    speed = SEARCH if method == 17 else zero_speed  # 17 searches at 0x6099:01, 34 at :02
    for dt in (0.02, 0.05, 0.1):  # a busy machine's gaps between frames
        sw, pos = _home(method, offset, zero_speed, dt, bank=bank)
        assert sw & 0x3400 == 0x1400, (dt, hex(sw))
        # the search looks at least every HOMING_CHECK_S: it stops within that much travel of where it
        # stops in 1 ms steps (a look per step), however long the step (before: speed x dt past it)
        assert abs(pos - ref) <= speed * HOMING_CHECK_S, (dt, pos, ref)


@pytest.mark.parametrize("bank", [False, True], ids=["scalar", "bank"])
@pytest.mark.parametrize(("method", "start_rad"), [(17, -1.5), (18, 1.5)])
def test_a_search_started_on_its_switch_homes_at_the_switch_edge(
    method: int, start_rad: float, bank: bool
) -> None:
    """A drive that coasted past its limit switch (a fault during the search) and homes again: it moves
    off the switch and homes at the edge (CiA 402 methods 17/18), instead of calling where it stands
    the switch position (before: the home offset read the distance past the switch off, 0.5 rad here)."""
    p = DriveParams()  # switches at -1 and +1 rad
    od = _od(p, method, 10_000, 10_000)
    d: Cia402Drive
    b = DriveBank([p]) if bank else None
    d = b.drives[0] if b is not None else Cia402Drive(p)
    d.position_rad = d._prev_target_rad = start_rad
    for k in range(round(RUN_S / 1e-3)):
        od.values[(Obj.CONTROLWORD, 0)] = _cw(k)
        if b is None:
            d.step(od, 1e-3)
        else:
            b.load_inputs(0, od)
            b.step(0, 1, 1e-3)
            b.store_outputs(0, od)
    sw, pos = int(od.values[(Obj.STATUSWORD, 0)]), int(od.values[(Obj.POSITION_ACTUAL, 0)])
    assert sw & 0x3400 == 0x1400, hex(sw)
    assert abs(pos - 10_000) <= 2 * SEARCH * HOMING_CHECK_S, pos  # at the edge (+ a look's travel, stop)
    edge = -1.0 if method == 17 else 1.0
    assert (d.position_rad - d._frame_rad > edge) == (method == 17)  # it stands off the switch
