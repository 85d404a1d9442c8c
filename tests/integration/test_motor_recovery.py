"""Recovery by name: a faulted raw-CAN motor cleared and enabled again through the documented call
(``backend.recover`` / ``Emulation.recover_motor``), by its family's own sequence, without moving.

Master: the real raw-CAN backend; emulators: ours, on the kit's virtual clock. What is judged is the
emulated motor's own state (enabled, its error code, where it is), against the family's published codes.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("can")

import fieldbus
from fieldbus.errors import FieldbusError
from fieldbus.testing import emulate

pytestmark = pytest.mark.timeout(300)
TURN = 2 * math.pi


def _network(tmp_path: Path, drive_map: str) -> Path:
    f = tmp_path / "legs.yaml"
    f.write_text(
        "cycle_time_us: 1000\nreceive_timeout_us: 500\nbuses:\n"
        f"  - {{name: legs, type: rawcan, interface: can0, can_interface: socketcan, slaves: "
        f"[{{name: 'm{{i}}', map: '{fieldbus.PDO_MAPS / (drive_map + '.yaml')}', node_id: 1, count: 2}}]}}\n"
    )
    return f


def _sim(emu: Any) -> Any:
    return emu.emulators["legs"].sim


def test_a_damiao_motor_that_faulted_is_enabled_again_by_name_and_does_not_move(tmp_path: Path) -> None:
    with emulate(_network(tmp_path, "damiao_dm_j4310")) as emu:
        legs, sim = emu.op["legs"], _sim(emu)
        legs.outputs["kp"][:], legs.outputs["kd"][:], legs.outputs["position"][:] = 20.0, 1.0, 0.3
        emu.cycles(800)
        assert sim.motor(2).position == pytest.approx(0.3, abs=0.01)
        emu.drive_fault("legs", "m1", 0xE)  # overload: the motor lets go
        emu.cycles(20)
        assert not sim.motor(2).enabled and sim.state[2].error == 0xE
        backend = emu.op.network.backend("legs")
        backend.clear_errors()  # the code is cleared, the motor stays disabled
        emu.cycles(20)
        assert not sim.motor(2).enabled and sim.state[2].error == 0

        legs.outputs["position"][1] = -1.0  # a target the controller left there must not be followed
        assert emu.recover_motor("legs", "m1")
        assert sim.motor(2).enabled and sim.state[2].error == 1  # ENABLED
        assert (legs.outputs["velocity"][1], legs.outputs["torque"][1]) == (0, 0)  # the gains kept: it holds
        assert legs.outputs["position"][1] == pytest.approx(legs.inputs["position"][1])
        at = sim.motor(2).position
        emu.cycles(200)
        assert abs(sim.motor(2).position - at) < 1e-3  # enabled, and still where it was
        assert backend.error_code("m1") == 1

        legs.outputs["position"][1] = 0.3
        emu.cycles(800)
        assert sim.motor(2).position == pytest.approx(0.3, abs=0.01)


def test_a_damiao_motor_in_velocity_mode_is_enabled_again_at_rest(tmp_path: Path) -> None:
    """The mode's own channel (``velocity.velocity``) is seeded at 0 too: enabling starts no motion."""
    with emulate(_network(tmp_path, "damiao_dm_j4310")) as emu:
        legs, sim = emu.op["legs"], _sim(emu)
        backend = emu.op.network.backend("legs")
        backend.set_mode("m1", "velocity")
        assert backend.mode("m1") == "velocity" and sim.state[2].reg(10) == 3
        legs.outputs["velocity.velocity"][1] = 2.0
        emu.cycles(300)
        assert sim.motor(2).velocity == pytest.approx(2.0, abs=0.05)
        emu.drive_fault("legs", "m1", 0xE)
        emu.cycles(20)
        assert not sim.motor(2).enabled
        assert emu.recover_motor("legs", "m1")
        assert legs.outputs["velocity.velocity"][1] == 0  # before: the 2 rad/s left there, sent again
        emu.cycles(300)
        assert sim.motor(2).enabled and abs(sim.motor(2).velocity) < 1e-3


def test_a_damiao_mode_switch_starts_from_rest_not_from_a_value_left_in_the_mode(tmp_path: Path) -> None:
    with emulate(_network(tmp_path, "damiao_dm_j4310")) as emu:
        legs, sim = emu.op["legs"], _sim(emu)
        backend = emu.op.network.backend("legs")
        backend.set_mode("m0", "velocity")
        legs.outputs["velocity.velocity"][0] = 2.0
        emu.cycles(300)
        assert sim.motor(1).velocity == pytest.approx(2.0, abs=0.05)
        backend.set_mode("m0", "mit")  # kp = kd = 0 in the image: the motor coasts
        legs.outputs["velocity"][0], legs.outputs["kd"][0] = 0.0, 2.0  # damped to rest
        emu.cycles(500)
        assert abs(sim.motor(1).velocity) < 0.05
        backend.set_mode("m0", "velocity")  # before: the 2 rad/s left in velocity.velocity went out again
        assert legs.outputs["velocity.velocity"][0] == 0
        emu.cycles(300)
        assert abs(sim.motor(1).velocity) < 1e-3
        backend.set_mode("m0", "position_velocity")
        assert legs.outputs["position_velocity.velocity"][0] == 0  # the speed limit: it holds
        assert legs.outputs["position_velocity.position"][0] == pytest.approx(legs.inputs["position"][0])


def test_an_odrive_axis_that_faulted_is_armed_again_by_name_and_holds_where_it_is(tmp_path: Path) -> None:
    with emulate(_network(tmp_path, "odrive_s1")) as emu:
        legs, sim = emu.op["legs"], _sim(emu)
        legs.outputs["position"][:] = 0.3 / TURN
        emu.cycles(800)
        assert sim.motor(1).position == pytest.approx(0.3, abs=0.01)
        emu.drive_fault("legs", "m0", 0x2000)  # MOTOR_OVER_TEMP: the axis goes IDLE
        emu.cycles(20)
        proto = sim._proto[1]
        assert sim.axes[1].state == proto.idle and sim.axes[1].error

        legs.outputs["position"][0] = 2.0  # turns: a stale target must not be followed
        assert emu.recover_motor("legs", "m0")
        assert sim.axes[1].state == proto.closed_loop and not sim.axes[1].error
        assert legs.outputs["position"][0] == pytest.approx(legs.inputs["position"][0])
        assert legs.outputs["velocity"][0] == 0 and legs.outputs["torque"][0] == 0
        at = sim.motor(1).position
        emu.cycles(300)
        assert abs(sim.motor(1).position - at) < 5e-3


def test_recovery_of_an_unknown_motor_is_refused_naming_the_bus_s_motors(tmp_path: Path) -> None:
    with (
        emulate(_network(tmp_path, "damiao_dm_j4310")) as emu,
        pytest.raises(FieldbusError, match="no slave 'nope'"),
    ):
        emu.recover_motor("legs", "nope")
