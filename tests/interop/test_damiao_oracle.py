"""The independent ``damiao-motor`` driver (PyPI, MIT licence; a test dependency) against our Damiao side.

1. Its ``DaMiaoController`` (pointed at python-can's ``virtual`` interface as it is: no adapter needed)
   enables our emulated DM-J4310, reads and writes its registers and runs each of its four modes. The
   emulator's physics run on a virtual clock the test advances: the driver sends at its own rate (a few
   commands), and the motor follows the last one between frames, as a real motor's loop does.
2. Its ``DaMiaoMotor`` encodes the values our master commanded; the bytes must equal the frames our
   master put on the bus (MIT within one raw step: it truncates, we round).
"""

from __future__ import annotations

import itertools
import os
import time
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

can = pytest.importorskip("can")
dm = pytest.importorskip(
    "damiao_motor", reason="damiao-motor is a test dependency: pip install 'fieldbus[dev]'"
)

from fieldbus import PDO_MAPS, open_network  # noqa: E402
from fieldbus.core.pdo import load_drive_map  # noqa: E402
from fieldbus.platform.clock import VirtualClock  # noqa: E402
from sim_slaves.damiao import DamiaoSimulator  # noqa: E402

pytestmark = pytest.mark.timeout(120)
MAP = Path(PDO_MAPS) / "damiao_dm_j4310.yaml"
_channels = itertools.count()


def wait_for(what: Callable[[], bool], limit_s: float = 10.0) -> None:
    """Wait for an event of the other threads (a generous limit against a hang, never a timing claim)."""
    end = time.monotonic() + limit_s
    while not what():
        assert time.monotonic() < end, "the event never came"
        time.sleep(0.002)


@pytest.fixture
def clock() -> VirtualClock:
    return VirtualClock(step_ns=1_000_000)


@pytest.fixture
def driver(clock: VirtualClock) -> Iterator[tuple[Any, Any, DamiaoSimulator]]:
    channel = f"fb-dmo-{os.getpid()}-{next(_channels)}"
    drive = load_drive_map(MAP)
    with (
        can.Bus(interface="virtual", channel=channel) as sim_bus,
        DamiaoSimulator(sim_bus, [(drive, 1)], clock=lambda: clock.now_ns() / 1e9) as sim,
    ):
        clock.watch(lambda _t: sim.idle())  # the motors' loops run as virtual time passes
        with warnings.catch_warnings():  # it passes python-can's deprecated bustype= argument
            warnings.simplefilter("ignore", DeprecationWarning)
            ctl = dm.DaMiaoController(channel=channel, bustype="virtual")
        try:
            motor = ctl.add_motor(motor_id=1, feedback_id=0x11, motor_type="4310")
            yield ctl, motor, sim
        finally:
            ctl._stop_polling()
            ctl.bus.shutdown()


def fresh_register(motor: Any, rid: int) -> float:
    """A register read from the motor, not the driver's cache."""
    with motor.registers_lock:
        motor.registers.pop(rid, None)
    return float(motor.get_register(rid, timeout=2.0))


def switch(motor: Any, mode: str) -> None:
    """The driver's mode switch as its ``ensure_control_mode`` does it (write register 10, read it back),
    with the read-back from the motor: damiao-motor 1.0.6 answers ``get_register`` from its cache once it
    holds the register, so its own verification sees the value from before the write and fails."""
    value = {"MIT": 1, "POS_VEL": 2, "VEL": 3, "FORCE_POS": 4}[mode]
    motor.write_register(10, value)
    assert fresh_register(motor, 10) == value


def commanded(sim: DamiaoSimulator, n: int) -> Callable[[], bool]:
    return lambda: sim.motor(1).commands >= n


def test_the_driver_reads_and_writes_our_emulators_registers(
    driver: tuple[Any, Any, DamiaoSimulator],
) -> None:
    _, motor, sim = driver
    assert fresh_register(motor, 7) == 0x11  # MST_ID
    assert fresh_register(motor, 8) == 1  # ESC_ID
    assert fresh_register(motor, 21) == 12.5 and fresh_register(motor, 22) == 30.0
    assert fresh_register(motor, 23) == 10.0
    motor.set_can_timeout(20)  # ms -> 400 units of 50 us
    wait_for(lambda: sim.state[1].reg(9) == 400)
    assert fresh_register(motor, 9) == 400
    motor.write_register(24, 1234.5)  # a float register
    wait_for(lambda: sim.state[1].reg(24) == 1234.5)
    assert fresh_register(motor, 24) == 1234.5


def at_its_own_rate(
    clock: VirtualClock, sim: DamiaoSimulator, send: Callable[[], None], n: int, s: float
) -> None:
    """The driver sends ``n`` commands, one every ``s`` seconds of the emulator's (virtual) time."""
    for _ in range(n):
        base = sim.motor(1).commands
        send()
        wait_for(commanded(sim, base + 1))
        clock.advance(round(s * 1e9))


def test_the_driver_enables_and_runs_each_mode(
    driver: tuple[Any, Any, DamiaoSimulator], clock: VirtualClock
) -> None:
    _, motor, sim = driver
    motor.enable()
    wait_for(lambda: motor.get_states().get("status") == "ENABLED")
    st = sim.motor(1)

    switch(motor, "MIT")
    at_its_own_rate(
        clock, sim, lambda: motor.send_cmd_mit(target_position=0.5, stiffness=30.0, damping=1.0), 5, 0.1
    )
    assert st.position == pytest.approx(0.5, abs=0.005)
    motor.send_cmd_mit(target_position=0.5, stiffness=30.0, damping=1.0)  # its reply tells the position
    wait_for(lambda: abs(motor.get_states()["pos"] - st.position) < 0.001)  # our reply, its decoder

    switch(motor, "VEL")
    at_its_own_rate(clock, sim, lambda: motor.send_cmd_vel(target_velocity=2.0), 3, 0.2)
    assert st.velocity == pytest.approx(2.0, abs=0.005)
    assert sim.state[1].mode_command == ("velocity", {"velocity": pytest.approx(2.0)})

    switch(motor, "POS_VEL")
    at_its_own_rate(
        clock, sim, lambda: motor.send_cmd_pos_vel(target_position=-0.5, velocity_limit=3.0), 3, 0.5
    )
    assert st.position == pytest.approx(-0.5, abs=0.005)

    switch(motor, "FORCE_POS")
    send = lambda: motor.send_cmd_force_pos(target_position=0.3, velocity_limit=2.0, torque_limit_ratio=0.5)  # noqa: E731
    at_its_own_rate(clock, sim, send, 3, 0.5)
    assert st.position == pytest.approx(0.3, abs=0.005)
    mode, values = sim.state[1].mode_command or ("", {})
    assert mode == "position_force" and values["torque"] == pytest.approx(5.0)  # 0.5 of TMAX 10 N·m
    assert sim.state[1].reg(10) == 4 and not sim.errors

    motor.disable()
    wait_for(lambda: motor.get_states().get("status") == "DISABLED")
    assert not st.enabled


def test_one_position_velocity_command_is_followed_to_its_target(
    driver: tuple[Any, Any, DamiaoSimulator], clock: VirtualClock
) -> None:
    """1.2 rad at 4 rad/s, one command and then only the driver's own polling: the motor's loop runs on
    between frames (an emulator stepped per frame stopped 0.087 rad short after 1.5 s)."""
    _, motor, sim = driver
    motor.enable()
    wait_for(lambda: motor.get_states().get("status") == "ENABLED")
    switch(motor, "POS_VEL")
    at_its_own_rate(
        clock, sim, lambda: motor.send_cmd_pos_vel(target_position=1.2, velocity_limit=4.0), 1, 1.5
    )
    st = sim.motor(1)
    assert st.position == pytest.approx(1.2, abs=0.005) and abs(st.velocity) < 0.005
    motor.send_cmd_pos_vel(target_position=1.2, velocity_limit=4.0)  # its reply tells where the motor is
    wait_for(lambda: abs(motor.get_states()["pos"] - 1.2) < 0.005)

    switch(motor, "VEL")
    at_its_own_rate(clock, sim, lambda: motor.send_cmd_vel(target_velocity=-3.0), 1, 1.0)
    assert st.velocity == pytest.approx(-3.0, abs=0.005)
    motor.send_cmd_vel(target_velocity=-3.0)
    wait_for(lambda: abs(motor.get_states()["vel"] + 3.0) < 0.02)  # its decoder: 12 bits over ±30 rad/s


class Capture:
    """A bus for the driver's encoder: keeps what it would send."""

    def __init__(self) -> None:
        self.sent: list[tuple[int, bytes]] = []

    def send(self, msg: Any) -> None:
        self.sent.append((msg.arbitration_id, bytes(msg.data)))


def test_the_driver_encodes_what_our_master_sent(tmp_path: Path) -> None:
    channel = f"fb-dmo-{os.getpid()}-{next(_channels)}"
    net = tmp_path / "net.yaml"
    net.write_text(
        "cycle_time_us: 1000\nreceive_timeout_us: 20000\nbuses:\n"
        f"  - {{name: arm, type: rawcan, interface: {channel}, can_interface: virtual,\n"
        f"     slaves: [{{name: j1, map: {MAP}, node_id: 1}}]}}\n"
    )
    drive = load_drive_map(MAP)
    cap = Capture()
    oracle = dm.DaMiaoMotor(motor_id=1, feedback_id=0x11, bus=cap, motor_type="4310")
    with (
        can.Bus(interface="virtual", channel=channel) as listener,
        can.Bus(interface="virtual", channel=channel) as sim_bus,
        DamiaoSimulator(sim_bus, [(drive, 1)]),
        open_network(net) as network,
    ):
        op = network.bring_up()
        out = op["arm"].outputs
        while listener.recv(timeout=0) is not None:
            pass
        out["position"][0], out["velocity"][0], out["kp"][0], out["kd"][0], out["torque"][0] = (
            1.2,
            -3.0,
            45,
            0.8,
            2.5,
        )
        op.exchange()
        ours = [bytes(m.data) for m in iter(lambda: listener.recv(timeout=0), None) if m.arbitration_id == 1]
        theirs = oracle.encode_cmd_msg(1.2, -3.0, 2.5, 45, 0.8)
        mine_x, their_x = int.from_bytes(ours[-1], "big"), int.from_bytes(theirs, "big")
        for shift, bits in ((48, 16), (36, 12), (24, 12), (12, 12), (0, 12)):  # position .. torque
            mask = (1 << bits) - 1
            assert abs(((mine_x >> shift) & mask) - ((their_x >> shift) & mask)) <= 1, (shift, ours, theirs)

        backend = network.backends[0]
        for mode, send in (
            ("velocity", lambda: oracle.send_cmd_vel(target_velocity=-3.0)),
            ("position_velocity", lambda: oracle.send_cmd_pos_vel(target_position=1.25, velocity_limit=2.5)),
            (
                "position_force",
                lambda: oracle.send_cmd_force_pos(1.25, velocity_limit=2.5, torque_limit_ratio=0.25),
            ),
        ):
            backend.set_mode("j1", mode)
            for name, value in (("position", 1.25), ("velocity", -3.0 if mode == "velocity" else 2.5)):
                if f"{mode}.{name}" in out.names:  # the mode's own channels
                    out[f"{mode}.{name}"][0] = value
            if mode == "position_force":
                out["position_force.torque"][0] = 2.5
            while listener.recv(timeout=0) is not None:
                pass
            op.exchange()
            frames = [(m.arbitration_id, bytes(m.data)) for m in iter(lambda: listener.recv(timeout=0), None)]
            sent = [f for f in frames if f[0] in (0x101, 0x201, 0x301)]
            cap.sent.clear()
            oracle._check_motor_status = lambda: None  # it would enable from its own (empty) state
            send()
            assert sent == cap.sent, (mode, sent, cap.sent)
