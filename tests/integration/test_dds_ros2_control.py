"""ros2_control's topic-based hardware interface on the served bus, as its JointStateTopicSystem writes.

The client writes what ``joint_state_topic_hardware_interface`` (ros-controls/topic_based_hardware_interfaces)
publishes from controller_manager's write(): a ``sensor_msgs/JointState`` with every joint's name and,
for velocity-only joints, only ``velocity`` filled, on ``/robot_joint_commands``; it reads
``/robot_joint_states``. Written with cyclonedds and the ROS 2 message definitions only
(tests/integration/dds/ros2_base_client.py); the served cycle runs in process on a virtual clock.
"""

from __future__ import annotations

import json
import math
import os
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("cyclonedds")

from cyclonedds.core import Policy, Qos
from cyclonedds.domain import DomainParticipant
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration

import fieldbus
from fieldbus.dds.gate import Deadline
from fieldbus.dds.participant import Participant
from fieldbus.dds.server import BusServer, ServeOptions
from fieldbus.testing import emulate

sys.path.insert(0, str(Path(__file__).parent / "dds"))
from ros2_base_client import JointState_

DEMO_JOINT = Path(fieldbus.__file__).resolve().parent / "data" / "demo_joint.yaml"
DOMAIN = 1 + (os.getpid() * 19 + 7) % 200
ENABLED = int(fieldbus.State402.OPERATION_ENABLED)
HW_QOS = Qos(
    Policy.Reliability.Reliable(duration(milliseconds=100)), Policy.History.KeepLast(1)
)  # rclcpp::QoS(1), as the interface
SENSOR_QOS = Qos(Policy.Reliability.BestEffort, Policy.History.KeepLast(5))  # SensorDataQoS


def _net(tmp_path: Path) -> Path:
    """Three demo joints in cyclic synchronous velocity (0x60FF mapped, mode 9)."""
    text = DEMO_JOINT.read_text().replace('value: 8, description: "modes of operation: CSP"', "value: 9")
    text = text.replace(
        "      - {index: 0x6060, sub_index: 0, type: int8, default: 8}",
        "      - {index: 0x6060, sub_index: 0, type: int8, default: 9}\n"
        "      - {index: 0x60FF, sub_index: 0, type: int32, factor: 20860.7568, unit: rad/s}",
    )
    (tmp_path / "csv_joint.yaml").write_text(text)
    net = tmp_path / "robot.yaml"
    net.write_text(
        "name: robot\ncycle_time_us: 1000\nbuses:\n  - name: arm\n    type: ethercat\n    interface: sim\n"
        f"    slaves: [{{name: 'joint{{i}}', map: {json.dumps(str(tmp_path / 'csv_joint.yaml'))}, count: 3}}]\n"
    )
    return net


class Served:
    def __init__(self, emu: Any, server: BusServer) -> None:
        self.emu, self.server, self.k = emu, server, 0

    def cycles(self, n: int, each: Any = None) -> None:
        for _ in range(n):
            if each is not None:
                each()
            self.server.step(self.k)
            self.k += 1
            self.emu.clock.sleep(self.emu.cycle_time_us / 1e6)

    @property
    def group(self) -> Any:
        return self.server.groups["arm"]


@pytest.fixture
def served(tmp_path: Path) -> Iterator[Served]:
    with emulate(_net(tmp_path), bring_up=False) as emu:
        server = BusServer(
            emu.network,
            Participant(DOMAIN, "lo"),
            ServeOptions(
                "robot",
                deadline=Deadline(50, 500),
                diagnostics_every=10**9,
                ros2_control=("robot_joint_commands", "robot_joint_states"),
            ),
            clock=emu.clock.now_ns,
        )
        server.attach(emu.bring_up())
        s = Served(emu, server)
        s.cycles(20)
        yield s


class HardwareInterface:
    """What JointStateTopicSystem does on the wire: commands out, states in (cyclonedds only)."""

    def __init__(self) -> None:
        dp = self.dp = DomainParticipant(DOMAIN)
        self.commands = DataWriter(dp, Topic(dp, "rt/robot_joint_commands", JointState_), qos=HW_QOS)
        self.states = DataReader(dp, Topic(dp, "rt/robot_joint_states", JointState_), qos=SENSOR_QOS)
        self.last: Any = None

    def write_velocity(self, velocities: list[float], names: list[str] | None = None) -> None:
        names = names or [f"joint{i}" for i in range(len(velocities))]
        self.commands.write(JointState_(name=names, velocity=velocities))

    def read(self) -> Any:
        for s in self.states.take(N=100):
            if isinstance(s, JointState_):
                self.last = s
        return self.last


def test_velocity_commands_on_the_joint_state_topic_move_the_joints_and_states_come_back(
    served: Served,
) -> None:
    hw = HardwareInterface()
    served.cycles(5)
    start = hw.read()
    assert start is not None and list(start.name) == ["joint0", "joint1", "joint2"]
    p0 = np.array(start.position)
    want = [0.5, -0.25, 0.0]
    # controller_manager writes every cycle at 100 Hz: every 10th bus cycle
    served.cycles(1500, lambda: hw.write_velocity(want) if served.k % 10 == 0 else None)
    assert served.group.ctrl.state.tolist() == [ENABLED] * 3
    got = hw.read()
    assert got.velocity == pytest.approx(want, abs=0.02)
    moved = np.array(got.position) - p0
    assert moved[0] > 0.3 and moved[1] < -0.15 and abs(moved[2]) < 0.01  # at most 1.5 s of motion
    # the interface stops writing: the gate holds, then latches the safe stop (the drives stop)
    served.cycles(700)
    assert served.group.gate.latched
    assert max(abs(v) for v in hw.read().velocity) < 0.05


def test_refused_commands_never_move_a_joint(served: Served) -> None:
    hw = HardwareInterface()
    served.cycles(5)
    p0 = np.array(hw.read().position)
    tc = served.server.topic_control
    assert tc is not None
    bad = [
        lambda: hw.write_velocity([math.nan, 0.0, 0.0]),
        lambda: hw.commands.write(JointState_(name=["joint0", "joint1", "joint2"], velocity=[1.0, 1.0])),
        lambda: hw.write_velocity([1.0], names=["elbow"]),
    ]
    for send in bad:
        served.cycles(50, lambda s=send: s() if served.k % 10 == 0 else None)
    assert tc.refusals["not_finite"] >= 5 and tc.refusals["wrong_length"] >= 5
    assert tc.refusals["unknown_joint"] >= 5
    assert tc.claim.owner is None  # nothing valid arrived: nobody took the joints
    assert np.allclose(hw.read().position, p0, atol=1e-3)
    # a second participant while the first owns the joints: refused, whatever it writes
    served.cycles(600, lambda: hw.write_velocity([0.1, 0.1, 0.1]) if served.k % 10 == 0 else None)
    rogue = HardwareInterface()
    before = tc.refusals["not_owner"]
    served.cycles(
        300,
        lambda: (
            (hw.write_velocity([0.1, 0.1, 0.1]), rogue.write_velocity([-2.0, -2.0, -2.0]))
            if served.k % 10 == 0
            else None
        ),
    )
    assert tc.refusals["not_owner"] - before >= 25
    assert min(hw.read().velocity) > 0.05
