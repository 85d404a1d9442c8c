"""Damiao DM-J motors (family damiao) through the public API against the Damiao emulator.

What the master puts on the bus is read by a listener on the virtual bus and decoded here from the
published layouts (MIT frame p16 v12 kp12 kd12 t12 big-endian; mode frames little-endian float32 /
uint16; register frames ``[id lo, id hi, op, reg, value LE]`` on 0x7FF), not by fieldbus's codec.
The emulator is our own code: tests/interop/test_damiao_oracle.py drives it with the independent
``damiao-motor`` driver.
"""

from __future__ import annotations

import itertools
import os
import struct
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

can = pytest.importorskip("can")

from fieldbus import PDO_MAPS, open_network  # noqa: E402
from fieldbus.core.pdo import load_drive_map  # noqa: E402
from fieldbus.errors import StateTransitionError  # noqa: E402
from sim_slaves.damiao import DamiaoSimulator  # noqa: E402

pytestmark = pytest.mark.timeout(120)
MAP = Path(PDO_MAPS) / "damiao_dm_j4310.yaml"
P, V, T = 12.5, 30.0, 10.0  # DM-J4310 PMAX, VMAX, TMAX
NODES = (1, 2, 3)
_channels = itertools.count()


def mit_command(data: bytes) -> dict[str, float]:
    """The published MIT command frame, field by field (bgkatz uint_to_float)."""
    x = int.from_bytes(data, "big")
    raw = {"position": x >> 48, "velocity": (x >> 36) & 0xFFF, "kp": (x >> 24) & 0xFFF}
    raw.update(kd=(x >> 12) & 0xFFF, torque=x & 0xFFF)
    ranges = {"position": (-P, P, 16), "velocity": (-V, V, 12), "kp": (0, 500, 12), "kd": (0, 5, 12)}
    ranges["torque"] = (-T, T, 12)
    return {k: raw[k] * (hi - lo) / ((1 << bits) - 1) + lo for k, (lo, hi, bits) in ranges.items()}


def drain(bus: can.BusABC) -> list[can.Message]:
    out = []
    while (msg := bus.recv(timeout=0)) is not None:
        out.append(msg)
    return out


class VirtualClock:
    """Seconds that pass only when a test says so (the emulator's CAN timeout runs on it)."""

    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


@pytest.fixture
def net_file(tmp_path: Path) -> Iterator[tuple[Path, str]]:
    channel = f"fb-dm-{os.getpid()}-{next(_channels)}"
    net = tmp_path / "net.yaml"
    net.write_text(
        "cycle_time_us: 1000\nreceive_timeout_us: 20000\nsafe_stop_after: 4\nbuses:\n"
        f"  - {{name: arm, type: rawcan, interface: {channel}, can_interface: virtual,\n"
        f"     slaves: [{{name: 'j{{i}}', map: {MAP}, node_id: 1, count: {len(NODES)}}}]}}\n"
    )
    yield net, channel


def test_bring_up_writes_and_reads_back_the_configuration(net_file: tuple[Path, str]) -> None:
    net, channel = net_file
    drive = load_drive_map(MAP)
    with (
        can.Bus(interface="virtual", channel=channel) as listener,
        can.Bus(interface="virtual", channel=channel) as sim_bus,
        DamiaoSimulator(
            sim_bus, [(drive, n) for n in NODES], dt_s=0.001, registers={2: {10: 3, 9: 0}}
        ) as sim,
        open_network(net) as network,
    ):
        network.bring_up()
        frames = drain(listener)
        requests = [bytes(m.data) for m in frames if m.arbitration_id == 0x7FF]
        for node in NODES:
            mine = [r for r in requests if r[0] == node and r[1] == 0]
            reads = {r[3] for r in mine if r[2] == 0x33}
            writes = {r[3]: struct.unpack("<I", r[4:])[0] for r in mine if r[2] == 0x55}
            assert {7, 21, 22, 23, 9, 10} <= reads, (node, reads)  # MST_ID, limits, read-backs
            assert writes == {10: 1, 9: 1000}, (node, writes)  # MIT, 50 ms in units of 50 us
            assert sim.state[node].reg(10) == 1 and sim.state[node].reg(9) == 1000
            assert sim.motor(node).enabled
        # replies come on MST_ID = id + 0x10
        assert {m.arbitration_id for m in frames if m.arbitration_id != 0x7FF} >= {0x11, 0x12, 0x13}
        assert not sim.errors


def test_a_pmax_mismatch_is_refused_naming_both_values(net_file: tuple[Path, str]) -> None:
    net, channel = net_file
    drive = load_drive_map(MAP)
    with (
        can.Bus(interface="virtual", channel=channel) as sim_bus,
        DamiaoSimulator(sim_bus, [(drive, n) for n in NODES], dt_s=0.001, registers={2: {21: 20.0}}) as sim,
        open_network(net) as network,
    ):
        with pytest.raises(
            StateTransitionError, match=r"j1 \(node 2\) has PMAX \(register 21\) = 20, .* says 12\.5"
        ):
            network.bring_up()
        assert not any(sim.motor(n).enabled for n in NODES)  # refused before any enable


def test_trajectory_at_1khz_mode_switch_fault_and_safe_stop(net_file: tuple[Path, str]) -> None:
    net, channel = net_file
    drive = load_drive_map(MAP)
    with (
        can.Bus(interface="virtual", channel=channel) as listener,
        can.Bus(interface="virtual", channel=channel) as sim_bus,
        # the motors' CAN timeout (TIMEOUT, 50 ms) on a clock that does not run: a loaded host that keeps
        # this test's master away for 50 ms would otherwise disable them, as it should (that is
        # test_the_motor_timeout_stops_a_motor_whose_master_died's subject, not this test's)
        DamiaoSimulator(sim_bus, [(drive, n) for n in NODES], dt_s=0.001, clock=VirtualClock()) as sim,
        open_network(net) as network,
    ):
        op = network.bring_up()
        backend = network.backends[0]
        out, inp = op["arm"].outputs, op["arm"].inputs
        out["kp"][:], out["kd"][:] = 30.0, 1.0
        target = np.array([0.6, -0.4, 1.0])
        errors = []
        for k in range(1000):  # 1 s of 1 kHz cycles (the emulator integrates 1 ms per command)
            out["position"][:] = target * min(1.0, k / 400)
            res = op.exchange()
            assert _fresh_or_held(res), (k, res.buses[0])
            errors.append(float(np.abs(inp["position"] - out["position"]).max()))
        assert max(errors[-100:]) < 0.02, max(errors[-100:])
        assert list(inp["motor_id"]) == list(NODES) and list(inp["error"]) == [1, 1, 1]
        assert list(inp["t_mos"]) == [30, 30, 30]

        # mode switch at run time: j0 (node 1) to velocity mode, frames on 0x200 + id
        backend.set_mode("j0", "velocity")
        assert sim.state[1].reg(10) == 3
        drain(listener)
        out["velocity.velocity"][:] = 3.0  # the velocity mode's own channel (float32 rad/s)
        for _ in range(300):
            assert _fresh_or_held(op.exchange())
        sent = [bytes(m.data) for m in drain(listener) if m.arbitration_id == 0x201]
        assert len(sent) == 300 and struct.unpack("<f", sent[-1][:4])[0] == pytest.approx(3.0)
        assert float(inp["velocity"][0]) == pytest.approx(3.0, abs=0.1)
        backend.set_mode("j0", "position_force")
        pf = ("position_force.position", "position_force.velocity", "position_force.torque")
        out[pf[0]][0], out[pf[1]][0], out[pf[2]][0] = 0.2, 2.0, 5.0
        for _ in range(1000):  # from about 1.5 rad at the 2 rad/s limit
            op.exchange()
        sent = [bytes(m.data) for m in drain(listener) if m.arbitration_id == 0x301]
        assert struct.unpack("<fHH", sent[-1]) == (pytest.approx(0.2), 200, 5000)  # 5 N·m of 10: 0.5 per unit
        assert float(inp["position"][0]) == pytest.approx(0.2, abs=0.01)
        backend.set_mode("j0", "mit")
        out["position"][0] = float(inp["position"][0])

        # a named fault, counted
        sim.inject_error(3, 0xE)
        op.exchange()
        assert backend.motor_faults == 1 and int(inp["error"][2]) == 0xE
        assert str(backend.faults[-1]) == "j2: motor error 0xE overload"
        assert backend.clear_errors() == [] and sim.state[3].error == 0

        # safe stop: every motor silent for safe_stop_after (4) cycles; the next commands carry kp = kd = 0
        for n in NODES:
            sim.drop_replies(n, 4)
        stops = [op.exchange().safe_stop for _ in range(4)]
        assert stops == [False, False, False, True]
        drain(listener)
        out["kp"][:], out["kd"][:], out["torque"][:] = 30.0, 1.0, 2.0  # the controller keeps pushing
        op.exchange()
        commands = {
            m.arbitration_id: mit_command(bytes(m.data)) for m in drain(listener) if m.arbitration_id in NODES
        }
        assert set(commands) == set(NODES)
        for cmd in commands.values():
            assert cmd["kp"] == 0.0 and cmd["kd"] == 0.0 and abs(cmd["torque"]) < 2 * T / 4095, cmd
        assert not sim.errors
        drain(listener)
        network.close()  # after the wind-down: a zero-gain command, then the disable frame, to every motor
        seen = drain(listener)
        tail = {n: [bytes(m.data) for m in seen if m.arbitration_id == n][-2:] for n in NODES}
        for n, (zero, disable) in tail.items():
            cmd = mit_command(zero)
            assert cmd["kp"] == 0.0 and cmd["kd"] == 0.0 and abs(cmd["torque"]) < 2 * T / 4095, (n, cmd)
            assert disable == bytes([0xFF] * 7 + [0xFD])
            assert not sim.motor(n).enabled and sim.state[n].error == 0


def test_the_motor_timeout_stops_a_motor_whose_master_died(net_file: tuple[Path, str]) -> None:
    net, channel = net_file
    drive = load_drive_map(MAP)
    clock = VirtualClock()
    with (
        can.Bus(interface="virtual", channel=channel) as sim_bus,
        DamiaoSimulator(sim_bus, [(drive, n) for n in NODES], dt_s=0.001, clock=clock) as sim,
        open_network(net) as network,
    ):
        op = network.bring_up()
        op["arm"].outputs["kp"][:] = 10.0
        for _ in range(10):
            clock.t += 0.001
            assert _fresh_or_held(op.exchange())
        clock.t += 0.049  # the master stops: 49 ms later the motors still hold (TIMEOUT 50 ms)
        sim.idle()
        assert all(sim.motor(n).enabled for n in NODES)
        clock.t += 0.002  # 51 ms: each motor lets go by itself and says why
        sim.idle()
        assert [sim.state[n].error for n in NODES] == [0xD] * 3
        assert not any(sim.motor(n).enabled for n in NODES)
        op.exchange()  # the master comes back: the fault is counted by name
        backend = network.backends[0]
        assert backend.motor_faults == 3
        assert {f.name for f in backend.faults} == {"communication lost"}


def _fresh_or_held(res: object) -> bool:
    """Fresh, or a miss the policy held (the threaded virtual bus can stall past a cycle's time-out on a
    loaded host): never a safe stop, which takes safe_stop_after misses in a row."""
    return bool(res.fresh) or not res.safe_stop  # type: ignore[attr-defined]


def test_each_motors_timeout_runs_from_its_own_last_command_and_enable() -> None:
    """The emulator's TIMEOUT per motor on a virtual clock, frame by frame (no master): a motor enabled
    later, with a shorter TIMEOUT, or commanded again, lets go at its own time, not at a time the
    emulator worked out before (it looks at every motor only when one may be due)."""
    drive = load_drive_map(MAP)
    clock = VirtualClock()
    channel = f"dm-timeout-{next(_channels)}"
    with (
        can.Bus(interface="virtual", channel=channel) as bus,
        can.Bus(interface="virtual", channel=channel) as tx,
    ):
        sim = DamiaoSimulator(bus, [(drive, n) for n in NODES], clock=clock)  # served here, no thread
        regs = drive.rawcan.damiao.registers  # type: ignore[union-attr]

        def frame(can_id: int, data: bytes) -> None:  # one frame, served as the testing kit serves it
            tx.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=False))
            assert sim.serve(0.0)

        def write(node: int, register: int, value: int) -> None:
            frame(regs.can_id, bytes([node, 0, regs.write, register]) + value.to_bytes(4, "little"))

        enable, command = bytes([0xFF] * 7 + [0xFC]), bytes(8)
        for n, units in zip(NODES, (1000, 1000, 200), strict=True):
            write(n, regs.timeout, units)  # 50, 50 and 10 ms (50 us units)
        frame(1, enable)
        clock.t = 0.030
        frame(2, enable)  # enabled 30 ms after motor 1
        frame(1, command)  # motor 1 commanded at 30 ms: due at 80 ms
        clock.t = 0.060
        frame(3, enable)  # due at 70 ms
        clock.t = 0.0699
        sim.idle()
        assert [sim.state[n].error for n in NODES] == [1, 1, 1]
        clock.t = 0.0701
        sim.idle()
        assert [sim.state[n].error for n in NODES] == [1, 1, 0xD]
        clock.t = 0.0799
        sim.idle()
        assert [sim.state[n].error for n in NODES] == [1, 1, 0xD]
        clock.t = 0.0801  # motor 2 (enabled at 30 ms) and motor 1 (commanded at 30 ms) both let go
        sim.idle()
        assert [sim.state[n].error for n in NODES] == [0xD, 0xD, 0xD]
        assert not any(sim.motor(n).enabled for n in NODES)
