"""ODrive controllers (family odrive, CANSimple) through the public API against the ODrive emulator.

The master's frames are read by a listener on the virtual bus and decoded here with struct from the
published layouts (id = node << 5 | command; little-endian), not with fieldbus's codec. The emulator is
our own code: tests/interop/test_odrive_oracle.py decodes with odriverobotics' DBC (odrive-can package).
"""

from __future__ import annotations

import itertools
import os
import struct
from collections import deque
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

can = pytest.importorskip("can")

from fieldbus import PDO_MAPS, open_network  # noqa: E402
from fieldbus.core.pdo import load_drive_map  # noqa: E402
from fieldbus.testing import emulate  # noqa: E402
from sim_slaves.odrive import OdriveSimulator  # noqa: E402

pytestmark = pytest.mark.timeout(120)
NODES = (1, 2, 3)
_channels = itertools.count()


class VirtualClock:
    """Seconds that pass only when a test says so (heartbeats and the watchdog run on it)."""

    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def drain(bus: can.BusABC | _Listener) -> list[can.Message]:
    out = []
    while (msg := bus.recv(timeout=0)) is not None:
        out.append(msg)
    return out


class _Listener:
    """The master's frames on a lockstep bus of the kit, as they reach the emulator (``recv`` as a bus's)."""

    def __init__(self, bus_emulator: Any) -> None:
        self.frames: deque[can.Message] = deque()
        bus_emulator.lockstep.handlers.insert(0, self.frames.append)

    def recv(self, timeout: float = 0) -> can.Message | None:
        return self.frames.popleft() if self.frames else None


class _Ticks:
    """``clock.t += dt`` moves the kit's virtual clock by ``dt`` seconds."""

    def __init__(self, clock: Any) -> None:
        self._clock = clock

    @property
    def t(self) -> float:
        return float(self._clock.now_ns()) / 1e9

    @t.setter
    def t(self, seconds: float) -> None:
        self._clock.advance_to(round(seconds * 1e9))


def net_file(tmp_path: Path, name: str) -> tuple[Path, str]:
    channel = f"fb-od-{os.getpid()}-{next(_channels)}"
    net = tmp_path / "net.yaml"
    net.write_text(
        "cycle_time_us: 1000\nreceive_timeout_us: 20000\nsafe_stop_after: 4\nbuses:\n"
        f"  - {{name: legs, type: rawcan, interface: {channel}, can_interface: virtual,\n"
        f"     slaves: [{{name: 'a{{i}}', map: {Path(PDO_MAPS) / name}, node_id: 1, count: {len(NODES)}}}]}}\n"
    )
    return net, channel


@pytest.fixture(params=["odrive_s1.yaml", "odrive_3_6.yaml"])
def setup(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[tuple[Path, str, str]]:
    net, channel = net_file(tmp_path, request.param)
    yield net, channel, request.param


def test_bring_up_trajectory_mode_switch_fault_and_safe_stop(setup: tuple[Path, str, str]) -> None:
    """On the kit's lockstep bus and virtual clock (1 ms of it per cycle): a loaded machine cannot
    make an exchange late. The master's frames are taken where the emulator receives them."""
    net, _channel, name = setup
    with emulate(net, bring_up=False) as emu:
        clock = _Ticks(emu.clock)
        listener = _Listener(emu.emulators["legs"])
        sim = emu.emulators["legs"].sim
        network = emu.network
        op = emu.bring_up()
        frames = drain(listener)
        for n in NODES:  # Set_Controller_Mode (3 position, 1 passthrough), then Set_Axis_State 8
            mode = [bytes(m.data) for m in frames if m.arbitration_id == n << 5 | 0x0B]
            state = [bytes(m.data) for m in frames if m.arbitration_id == n << 5 | 0x07]
            assert [struct.unpack("<II", d) for d in mode] == [(3, 1)], n
            assert [struct.unpack("<I", d[:4])[0] for d in state] == [8], n
            assert sim.axes[n].state == 8
        backend = network.backends[0]
        out, inp = op["legs"].outputs, op["legs"].inputs
        target = np.array([0.5, -0.25, 1.0])  # turns
        errors = []
        sent = []
        for k in range(1000):  # 1 s of 1 kHz cycles
            clock.t += 0.001
            out["position"][:] = target * min(1.0, k / 400)
            res = op.exchange()
            assert res.fresh, (k, res.buses[0])
            errors.append(float(np.abs(inp["position"] - out["position"]).max()))
            if k % 100 == 99:
                sent += drain(listener)
        assert max(errors[-100:]) < 0.01, max(errors[-100:])
        assert list(inp["axis_state"]) == [8, 8, 8] and list(inp["axis_error"]) == [0, 0, 0]
        pos = [struct.unpack("<fhh", bytes(m.data)) for m in sent if m.arbitration_id == 3 << 5 | 0x0C]
        rtr = [m for m in sent if m.arbitration_id == 3 << 5 | 0x09 and m.is_remote_frame]
        assert len(pos) == 1000 and len(rtr) == 1000 and pos[-1][0] == pytest.approx(1.0)

        # position -> velocity at run time: Set_Controller_Mode (2, 1), then Set_Input_Vel frames
        backend.set_mode("a0", "velocity")
        out["velocity"][:] = 2.0
        for _ in range(300):
            clock.t += 0.001
            assert op.exchange().fresh
        sent = drain(listener)
        assert [struct.unpack("<II", bytes(m.data)) for m in sent if m.arbitration_id == 1 << 5 | 0x0B] == [
            (2, 1)
        ]
        vel = [struct.unpack("<ff", bytes(m.data)) for m in sent if m.arbitration_id == 1 << 5 | 0x0D]
        assert len(vel) == 300 and vel[-1] == (2.0, 0.0)
        assert float(inp["velocity"][0]) == pytest.approx(2.0, abs=0.05)

        # a fault named from the heartbeat's bits
        bit = 0x00040000 if name == "odrive_3_6.yaml" else 0x00002000
        sim.inject_error(3, bit)
        for _ in range(3):
            clock.t += 0.001
            op.exchange()
        assert (
            backend.motor_faults == 1 and int(inp["axis_error"][2]) == bit and int(inp["axis_state"][2]) == 1
        )
        assert str(backend.faults[-1]) == f"a2: motor error 0x{bit:X} " + (
            "OVER_TEMP" if name == "odrive_3_6.yaml" else "MOTOR_OVER_TEMP"
        )
        assert backend.clear_errors() == []
        clock.t += 0.001
        op.exchange()
        assert sim.axes[3].error == 0

        # safe stop: replies missing for safe_stop_after (4) cycles; then IDLE requested, no set-point
        for n in NODES:
            sim.drop_replies(n, 4)
        stops = []
        for _ in range(4):
            clock.t += 0.001
            stops.append(op.exchange().safe_stop)
        assert stops == [False, False, False, True]
        drain(listener)
        for _ in range(3):
            clock.t += 0.001
            op.exchange()
        seen = drain(listener)
        for n in NODES:
            idle = [
                struct.unpack("<I", bytes(m.data)[:4])[0] for m in seen if m.arbitration_id == n << 5 | 0x07
            ]
            setpoints = [
                m for m in seen if m.arbitration_id >> 5 == n and (m.arbitration_id & 0x1F) in (0xC, 0xD, 0xE)
            ]
            assert idle == [1] and setpoints == [], n
            assert sim.axes[n].state == 1
        assert not sim.errors


def test_the_watchdog_idles_an_axis_whose_master_died(tmp_path: Path) -> None:
    """On the kit's lockstep bus and virtual clock: a loaded machine cannot stall an exchange."""
    net, _channel = net_file(tmp_path, "odrive_s1.yaml")
    with emulate(net, bring_up=False) as emu:
        clock = _Ticks(emu.clock)
        sim = emu.emulators["legs"].sim
        for n in NODES:
            sim.axes[n].watchdog_s = 0.050
        network = emu.network
        op = emu.bring_up()
        for _ in range(10):
            clock.t += 0.001
            assert op.exchange().fresh
        clock.t += 0.049
        sim.idle()
        assert all(sim.axes[n].state == 8 for n in NODES)
        clock.t += 0.002
        sim.idle()
        assert [sim.axes[n].state for n in NODES] == [1, 1, 1]
        assert all(sim.axes[n].error == 0x01000000 for n in NODES)
        op.exchange()
        backend = network.backends[0]
        assert backend.motor_faults == 3 and {f.name for f in backend.faults} == {"WATCHDOG_TIMER_EXPIRED"}


def _fresh_or_held(res: object) -> bool:
    """Fresh, or a miss the policy held (the threaded virtual bus can stall past a cycle's time-out on a
    loaded host): never a safe stop, which takes safe_stop_after misses in a row."""
    return bool(res.fresh) or not res.safe_stop  # type: ignore[attr-defined]


def test_bring_up_asks_for_the_heartbeat_it_did_not_hear(tmp_path: Path) -> None:
    """Every emulated axis sends its first heartbeat before the master's bus exists and its heartbeat timer
    is stopped (a virtual clock that does not run): the bring-up asks for one by RTR and goes on."""
    net, channel = net_file(tmp_path, "odrive_s1.yaml")
    drive = load_drive_map(Path(PDO_MAPS) / "odrive_s1.yaml")
    clock = VirtualClock()
    with (
        can.Bus(interface="virtual", channel=channel) as sim_bus,
        can.Bus(interface="virtual", channel=channel) as listener,
        OdriveSimulator(sim_bus, [(drive, n) for n in NODES], dt_s=0.001, clock=clock) as sim,
    ):
        heard: set[int] = set()
        for _ in range(200):  # the emulator's first idle pass sends one heartbeat per axis
            msg = listener.recv(timeout=0.05)
            if msg is not None and msg.arbitration_id & 0x1F == 0x01:
                heard.add(msg.arbitration_id >> 5)
            if heard == set(NODES):
                break
        assert heard == set(NODES)
        with open_network(net) as network:
            op = network.bring_up()
            assert [sim.axes[n].state for n in NODES] == [8, 8, 8]
            assert _fresh_or_held(op.exchange())


def test_an_axis_that_refuses_to_arm_stops_the_bring_up_naming_it_and_what_it_did_not_say(
    tmp_path: Path,
) -> None:
    """On the kit's virtual clock: axis 2 has an error set, so it refuses CLOSED_LOOP_CONTROL and its
    heartbeats keep saying IDLE; op() waits a bounded time for a heartbeat saying 8, then fails naming
    a1 and the awaited state (the others' waits were met), and the failed bring-up lets every axis go."""
    from fieldbus.errors import StateTransitionError

    net, _channel = net_file(tmp_path, "odrive_s1.yaml")
    with emulate(net, bring_up=False) as emu:
        sim = emu.emulators["legs"].sim
        sim.inject_error(2, 0x00002000)
        start = emu.clock.now_ns()
        with pytest.raises(StateTransitionError, match=r"a1 \(a heartbeat with axis state 8\)") as err:
            emu.bring_up()
        assert err.value.slave == "a1" and "a0" not in str(err.value) and "a2" not in str(err.value)
        # the failed bring-up's stop sent every axis IDLE after its request for closed loop
        for n in NODES:
            states = [struct.unpack_from("<I", d)[0] for c, d, _ in sim.axes[n].frames if c == 0x07]
            assert states[-2:] == [8, 1] and sim.axes[n].state == 1, (n, states)
        waited_s = (emu.clock.now_ns() - start) / 1e9
        assert 2.0 <= waited_s < 60.0, waited_s  # the bound (2 s of the clock), not forever


def test_bring_up_writes_the_map_s_endpoints_and_reads_them_back(tmp_path: Path) -> None:
    """A map for one firmware build lists the watchdog's endpoints under ``config:``: the bring-up writes
    each through RxSdo and reads it back (TxSdo); the emulated controller then holds them, and its
    watchdog (50 ms of the kit's virtual clock) idles an axis whose master stops sending."""
    text = (Path(PDO_MAPS) / "odrive_s1.yaml").read_text()
    config = (
        "    config:\n"
        "      - {name: watchdog_timeout, endpoint: 0x1B0, type: float32, value: 0.05}\n"
        "      - {name: enable_watchdog, endpoint: 0x1B1, type: bool, value: 1}\n"
    )
    drive = tmp_path / "odrive_wd.yaml"
    drive.write_text(
        text.replace("name: odrive_s1", "name: odrive_wd").replace(
            "    heartbeat_ms: 100", config + "    heartbeat_ms: 100"
        )
    )
    net = tmp_path / "net.yaml"
    net.write_text(
        "cycle_time_us: 1000\nreceive_timeout_us: 20000\nbuses:\n"
        f"  - {{name: legs, type: rawcan, interface: can0, slaves: [{{name: 'a{{i}}', map: '{drive}', "
        "node_id: 1, count: 2}]}\n"
    )
    with emulate(net, bring_up=False) as emu:
        sim = emu.emulators["legs"].sim
        for n in (1, 2):
            sim.axes[n].endpoints.update({0x1B0: struct.pack("<f", 0.0), 0x1B1: struct.pack("<I", 0)})
        sim._watchdog_ep = (0x1B0, 0x1B1)  # the emulated build's endpoint ids
        op = emu.bring_up()
        for n in (1, 2):
            assert sim.endpoint(n, 0x1B0) == pytest.approx(0.05) and sim.endpoint(n, 0x1B1, "<I") == 1
            rxsdo = [d for c, d, _ in sim.axes[n].frames if c == 0x04]
            assert [(d[0], struct.unpack_from("<H", d, 1)[0]) for d in rxsdo] == [
                (1, 0x1B0), (0, 0x1B0), (1, 0x1B1), (0, 0x1B1),
            ]  # fmt: skip
        clock = _Ticks(emu.clock)
        for _ in range(5):
            clock.t += 0.001
            assert op.exchange().fresh
        clock.t += 0.060  # no set-point for longer than the written 50 ms
        sim.idle()
        assert [sim.axes[n].state for n in (1, 2)] == [1, 1]


def test_an_endpoint_that_reads_back_otherwise_stops_the_bring_up_naming_it(tmp_path: Path) -> None:
    from fieldbus.errors import StateTransitionError

    text = (Path(PDO_MAPS) / "odrive_s1.yaml").read_text()
    config = "    config:\n      - {name: watchdog_timeout, endpoint: 0x1B0, type: float32, value: 0.05}\n"
    drive = tmp_path / "odrive_wd.yaml"
    drive.write_text(text.replace("    heartbeat_ms: 100", config + "    heartbeat_ms: 100"))
    net = tmp_path / "net.yaml"
    net.write_text(
        "cycle_time_us: 1000\nreceive_timeout_us: 20000\nbuses:\n"
        f"  - {{name: legs, type: rawcan, interface: can0, slaves: [{{name: a0, map: '{drive}', node_id: 1}}]}}\n"
    )
    with emulate(net, bring_up=False) as emu:
        sim = emu.emulators["legs"].sim
        sim.axes[1].endpoints[0x1B0] = struct.pack("<f", 0.0)
        real = sim.handle

        def stuck(msg: can.Message) -> can.Message | None:  # a read-only endpoint: writes are ignored
            if msg.arbitration_id == 1 << 5 | 0x04 and msg.data[0] == 1:
                return None
            return real(msg)

        sim.handle = stuck
        with pytest.raises(StateTransitionError, match=r"a0 endpoint watchdog_timeout \(432\) reads back 0"):
            emu.bring_up()
