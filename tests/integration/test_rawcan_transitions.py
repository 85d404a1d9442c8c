"""No transition starts a raw-CAN motor (S12): after a safe stop's clear, a recovery or a mode switch, the
first command frames hold the motor where it is, whatever the image held from before.

Master: the real raw-CAN backend; motors: our MIT and Damiao emulators, on the kit's virtual clock. The
command frames are taken off the lockstep bus by a handler of the test's own and decoded here from the
published MIT layout (bgkatz motorcontrol / CubeMars AK manual, "MIT mode": p16 v12 kp12 kd12 t12,
big-endian, ``uint = (x - min) * 4095 / (max - min)``), not by fieldbus's codec; the motion is the
emulator's own state.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("can")

import fieldbus
from fieldbus.testing import emulate

pytestmark = pytest.mark.timeout(300)
RANGES = {  # the AK80-9's MIT ranges (its manual's limits table): (min, max, bits)
    "position": (-12.5, 12.5, 16),
    "velocity": (-50.0, 50.0, 12),
    "kp": (0.0, 500.0, 12),
    "kd": (0.0, 5.0, 12),
    "torque": (-18.0, 18.0, 12),
}
STALE = {"position": 5.0, "velocity": 3.0, "torque": 2.0}  # a set-point from before the stop, far away


def decode_mit(data: bytes) -> dict[str, float]:
    """The published MIT command frame, field by field (engineering units)."""
    x = int.from_bytes(data, "big")
    raw = {
        "position": x >> 48,
        "velocity": (x >> 36) & 0xFFF,
        "kp": (x >> 24) & 0xFFF,
        "kd": (x >> 12) & 0xFFF,
        "torque": x & 0xFFF,
    }
    return {n: raw[n] * (hi - lo) / ((1 << bits) - 1) + lo for n, (lo, hi, bits) in RANGES.items()}


def lsb(name: str) -> float:
    lo, hi, bits = RANGES[name]
    return (hi - lo) / ((1 << bits) - 1)


def _network(tmp_path: Path, drive_map: str, extra: str = "") -> Path:
    f = tmp_path / "legs.yaml"
    f.write_text(
        f"cycle_time_us: 1000\nreceive_timeout_us: 500\nsafe_stop_after: 3\n{extra}buses:\n"
        f"  - {{name: legs, type: rawcan, interface: can0, can_interface: socketcan, slaves: "
        f"[{{name: 'm{{i}}', map: '{fieldbus.PDO_MAPS / (drive_map + '.yaml')}', node_id: 1, count: 2}}]}}\n"
    )
    return f


class Wire:
    """Every MIT command frame the motors get, decoded per node, in order (a handler on the lockstep bus)."""

    def __init__(self, emu: Any) -> None:
        self.frames: dict[int, list[dict[str, float]]] = {1: [], 2: []}
        emu.emulators["legs"].lockstep.handlers.append(self._take)

    def _take(self, msg: Any) -> None:
        data = bytes(msg.data)
        if msg.arbitration_id in self.frames and len(data) == 8 and data[:7] != b"\xff" * 7:
            self.frames[msg.arbitration_id].append(decode_mit(data))

    def clear(self) -> None:
        for v in self.frames.values():
            v.clear()


def _holds(cmd: dict[str, float], at: float) -> None:
    """A command that moves nothing: the position read, no speed, no gains, no torque."""
    assert abs(cmd["position"] - at) <= 2 * lsb("position"), (cmd, at)
    assert abs(cmd["velocity"]) <= lsb("velocity") and abs(cmd["torque"]) <= lsb("torque"), cmd
    assert cmd["kp"] == 0.0 and cmd["kd"] == 0.0, cmd


def _latch_with_stale_targets(emu: Any, out: Any) -> None:
    """Hold at 0.4 rad, latch the safe stop (replies lost), then write a far set-point while latched."""
    out["kp"][:], out["kd"][:], out["position"][:] = 40.0, 1.5, 0.4
    emu.cycles(600)
    emu.lose_cycles("legs", 3)
    for _ in range(3):
        emu.op.exchange()
    assert emu.op.result.safe_stop
    for _ in range(5):  # the safe frames (kp = kd = torque = 0) go out; the image keeps 5 rad, 3 rad/s
        out["position"][:], out["velocity"][:], out["torque"][:] = (
            STALE["position"],
            STALE["velocity"],
            STALE["torque"],
        )
        out["kp"][:], out["kd"][:] = 40.0, 1.5
        emu.op.exchange()


def test_after_a_clear_the_first_frames_hold_the_actual_position_and_a_gain_alone_moves_nothing(
    tmp_path: Path,
) -> None:
    with emulate(_network(tmp_path, "cubemars_ak80_9_mit")) as emu:
        op, sim = emu.op, emu.emulators["legs"].sim
        out, inp = op["legs"].outputs, op["legs"].inputs
        wire = Wire(emu)
        _latch_with_stale_targets(emu, out)
        at = [sim.motor(n).position for n in (1, 2)]
        assert all(abs(p - 0.4) < 0.02 for p in at), at
        op.clear_safe_stop()
        while op.result.safe_stop:
            op.exchange()  # release_after fresh cycles: still the safe frames
        wire.clear()
        op.exchange()  # the first cycle after the latch opened, nothing written since
        for n in (1, 2):
            assert len(wire.frames[n]) == 1
            _holds(wire.frames[n][0], at[n - 1])  # before: position 5.0 rad, velocity 3.0 rad/s on the wire
        assert list(out["position"]) == pytest.approx(list(inp["position"]), abs=1e-3)

        out["kp"][:], out["kd"][:] = 40.0, 1.5  # the controller re-arms its gains, nothing else
        emu.cycles(400)
        for n in (1, 2):  # before: the motors ran to the stale 5 rad at 3 rad/s
            assert abs(sim.motor(n).position - at[n - 1]) < 0.01, (n, sim.motor(n).position, at)
        out["position"][:] = math.nan  # NaN keeps the seed, never the stale set-point sent before
        emu.cycles(200)
        for n in (1, 2):
            assert abs(sim.motor(n).position - at[n - 1]) < 0.01, (n, sim.motor(n).position)
            assert abs(wire.frames[n][-1]["position"] - at[n - 1]) <= 2 * lsb("position")
        out["position"][:] = 1.0  # a new command after the transition is followed
        emu.cycles(800)
        assert [sim.motor(n).position for n in (1, 2)] == pytest.approx([1.0, 1.0], abs=0.02)


def test_a_fault_and_nan_during_the_release_leave_only_the_hold_on_the_wire(tmp_path: Path) -> None:
    with emulate(_network(tmp_path, "cubemars_ak80_9_mit")) as emu:
        op, sim = emu.op, emu.emulators["legs"].sim
        out = op["legs"].outputs
        wire = Wire(emu)
        _latch_with_stale_targets(emu, out)
        op.clear_safe_stop()
        op.exchange()
        assert op.result.bus("legs").release_pending
        emu.lose_cycles("legs", 1)  # a fault in the middle of the release: the clear is cancelled
        out["position"][:] = math.nan  # and NaN written meanwhile
        for _ in range(20):
            op.exchange()
            assert op.result.safe_stop
        sent = [c for n in (1, 2) for c in wire.frames[n][-20:]]
        assert all(c["kp"] == 0.0 and c["kd"] == 0.0 and abs(c["torque"]) <= lsb("torque") for c in sent)
        at = [sim.motor(n).position for n in (1, 2)]
        op.clear_safe_stop()
        while op.result.safe_stop:
            out["position"][:], out["kp"][:] = math.nan, 40.0  # the controller pushes during the release
            op.exchange()
        wire.clear()
        out["position"][:], out["kp"][:], out["kd"][:] = math.nan, 40.0, 1.5  # after it: gains and a NaN
        emu.cycles(300)
        for n in (1, 2):
            first = wire.frames[n][0]
            assert abs(first["position"] - at[n - 1]) <= 2 * lsb("position"), first  # the seed, not 5 rad
            assert abs(first["velocity"]) <= lsb("velocity") and abs(first["torque"]) <= lsb("torque")
            assert abs(sim.motor(n).position - at[n - 1]) < 0.01, (n, sim.motor(n).position, at)


def test_a_step_limit_ramps_from_where_the_motor_is_after_a_clear(tmp_path: Path) -> None:
    """With a ``max_step`` on position, the rules' reference is the seed: no ramp from the stale 5 rad."""
    src = (fieldbus.PDO_MAPS / "cubemars_ak80_9_mit.yaml").read_text()
    (tmp_path / "ak80_step.yaml").write_text(src + "limits:\n  position: {max_step: 0.002}\n")
    net = tmp_path / "legs.yaml"
    net.write_text(
        "cycle_time_us: 1000\nreceive_timeout_us: 500\nsafe_stop_after: 3\nbuses:\n"
        "  - {name: legs, type: rawcan, interface: can0, can_interface: socketcan, slaves: "
        f"[{{name: 'm{{i}}', map: '{tmp_path / 'ak80_step.yaml'}', node_id: 1, count: 2}}]}}\n"
    )
    with emulate(net) as emu:
        op, sim = emu.op, emu.emulators["legs"].sim
        out = op["legs"].outputs
        wire = Wire(emu)
        out["kp"][:], out["kd"][:] = 40.0, 1.5
        for k in range(300):  # to 0.4 rad within the step
            out["position"][:] = min(0.4, 0.002 * k)
            op.exchange()
        emu.cycles(300)
        emu.lose_cycles("legs", 3)
        for k in range(3 + 2000):  # latched; the controller's set-point runs on towards 5 rad
            out["position"][:] = min(5.0, 0.4 + 0.002 * k)
            op.exchange()
        assert op.result.safe_stop and float(out["position"][0]) == pytest.approx(4.4, abs=0.01)
        at = [sim.motor(n).position for n in (1, 2)]
        op.clear_safe_stop()
        while op.result.safe_stop:
            op.exchange()
        wire.clear()
        out["kp"][:], out["kd"][:] = 40.0, 1.5
        emu.cycles(300)
        for n in (1, 2):
            assert max(abs(c["position"] - at[n - 1]) for c in wire.frames[n]) <= 2 * lsb("position")
            assert abs(sim.motor(n).position - at[n - 1]) < 0.01  # before: it ramped from 4.4 rad


def test_a_recovered_damiao_motor_given_nan_holds_where_it_is(tmp_path: Path) -> None:
    """recover() seeds the set-points and the rules' reference: a NaN after it keeps the seed, not the
    target the controller sent while the motor was disabled."""
    with emulate(_network(tmp_path, "damiao_dm_j4310")) as emu:
        legs, sim = emu.op["legs"], emu.emulators["legs"].sim
        legs.outputs["kp"][:], legs.outputs["kd"][:], legs.outputs["position"][:] = 20.0, 1.0, 0.3
        emu.cycles(800)
        emu.drive_fault("legs", "m1", 0xE)  # overload: the motor lets go
        legs.outputs["position"][1] = -1.0  # sent while it is disabled
        emu.cycles(20)
        assert not sim.motor(2).enabled
        emu.op.network.backend("legs").clear_errors()
        assert emu.recover_motor("legs", "m1")
        at = sim.motor(2).position
        legs.outputs["position"][1] = math.nan
        emu.cycles(300)
        assert abs(sim.motor(2).position - at) < 1e-3, (sim.motor(2).position, at)  # before: ran to -1 rad


def test_a_damiao_mode_switch_starts_from_where_the_motor_is(tmp_path: Path) -> None:
    """set_mode seeds too: velocity mode runs neither the MIT feed-forward speed the image held nor a
    speed left in the mode's own channel (``velocity.velocity``) from before."""
    with emulate(_network(tmp_path, "damiao_dm_j4310")) as emu:
        legs, sim = emu.op["legs"], emu.emulators["legs"].sim
        out = legs.outputs
        out["kp"][:], out["kd"][:], out["position"][:], out["velocity"][:] = 20.0, 1.0, 0.3, 0.0
        emu.cycles(800)
        out["velocity"][0] = 4.0  # an MIT feed-forward the controller left there
        out["velocity.velocity"][0] = 4.0  # and a speed left in the velocity mode's channel
        emu.op.network.backend("legs").set_mode("m0", "velocity")
        assert out["velocity"][0] == 0.0 and out["position"][0] == pytest.approx(legs.inputs["position"][0])
        assert out["velocity.velocity"][0] == 0.0
        at = sim.motor(1).position
        emu.cycles(300)
        assert abs(sim.motor(1).position - at) < 0.01, (sim.motor(1).position, at)  # before: 4 rad/s
        out["velocity.velocity"][0] = 2.0  # the velocity mode's own channel (float32 rad/s)
        emu.cycles(300)
        assert float(legs.inputs["velocity"][0]) == pytest.approx(2.0, abs=0.1)


def test_a_clear_that_opens_at_once_also_seeds_the_hold(tmp_path: Path) -> None:
    """The latch opens inside clear_safe_stop() when the bus already had release_after fresh cycles: the
    next exchange's frames hold too (no exchange saw the release)."""
    with emulate(_network(tmp_path, "cubemars_ak80_9_mit")) as emu:
        op, sim = emu.op, emu.emulators["legs"].sim
        out = op["legs"].outputs
        wire = Wire(emu)
        _latch_with_stale_targets(emu, out)
        emu.cycles(20)  # healthy again, still latched: more than release_after fresh cycles
        at = [sim.motor(n).position for n in (1, 2)]
        assert op.result.safe_stop
        assert op.clear_safe_stop()  # open now
        wire.clear()
        out["kp"][:], out["kd"][:] = 40.0, 1.5
        emu.cycles(200)
        for n in (1, 2):
            first = wire.frames[n][0]
            assert abs(first["position"] - at[n - 1]) <= 2 * lsb("position"), first  # before: 5.0 rad
            assert abs(first["velocity"]) <= lsb("velocity"), first  # before: 3.0 rad/s
            assert abs(sim.motor(n).position - at[n - 1]) < 0.01
