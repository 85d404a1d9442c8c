"""``fieldbus serve`` of multi-axis slaves (issue 25 item 4): one joint per axis, named ``<slave>.axis<k>``.

In process on the sim emulator with a virtual clock, as test_dds_diagnostics.py: the server's cycle is
stepped by the test; the command goes in and the JointState comes out through real DDS topics
(Cyclone DDS on loopback), read back by a reader of the test's own. Our own code serves the bus.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("cyclonedds")

from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic

import fieldbus
from fieldbus.core.cia402 import State402
from fieldbus.dds import messages as m
from fieldbus.dds.gate import Deadline
from fieldbus.dds.participant import RELIABLE, Participant, service_names
from fieldbus.dds.server import BusServer, ServeOptions
from fieldbus.testing import emulate

MAPS = Path(__file__).resolve().parents[2] / "pdo_maps"
TWO_AXIS = MAPS / "generic_cia402_2axis.yaml"
JOINTS = ["shoulder.axis1", "shoulder.axis2", "elbow.axis1", "elbow.axis2"]
OFFSETS = np.array([1000.0, -2000.0, 3000.0, 500.0])  # counts: each axis's own move from where it stood


NO_DEADLINE = Deadline(hold_after=60_000, stop_after=120_000)  # one command, then cycles without one


def _network(tmp_path: Path) -> Path:
    net = tmp_path / "arm.yaml"
    net.write_text(
        "name: arm\ncycle_time_us: 1000\nbuses:\n  - name: arm\n    type: ethercat\n    interface: sim\n"
        f"    slaves:\n      - {{name: shoulder, map: {TWO_AXIS}}}\n      - {{name: elbow, map: {TWO_AXIS}}}\n"
    )
    return net


def _domain() -> int:
    return 1 + (os.getpid() * 11 + 5) % 200


def _run_until(emu: fieldbus.testing.Emulation, server: BusServer, done: object, cycles: int) -> None:
    """Step the server; DDS delivers between cycles in wall time, so each cycle yields the CPU a little."""

    def step(k: int) -> bool:
        server.step(k)
        time.sleep(0.001)
        return bool(done())  # type: ignore[operator]

    emu.run(step, cycles=cycles)


def test_a_served_two_axis_slave_has_a_joint_per_axis_with_its_own_position(tmp_path: Path) -> None:
    with emulate(_network(tmp_path), bring_up=False) as emu:
        server = BusServer(
            emu.network, Participant(_domain(), "lo"), ServeOptions("arm", deadline=NO_DEADLINE)
        )
        server.attach(emu.bring_up())
        (name,) = server.groups
        g = server.groups[name]
        assert list(g.axes) == JOINTS and server.describe()["groups"][name]["axes"] == JOINTS
        dp = server.participant.dp
        states = DataReader(dp, Topic(dp, g.topics["joint_states"], m.JointState))
        axis_states = DataReader(dp, Topic(dp, g.topics["axis_state"], m.AxisState))
        commands = DataWriter(dp, Topic(dp, g.topics["command"], m.JointCommand))
        assert g.ctrl is not None
        g.ctrl.set_goal(fieldbus.Goal.ENABLE)
        emu.run(server.step, cycles=300)
        assert emu.drive_states("arm") == [State402.OPERATION_ENABLED] * 4
        start = emu.op[name].inputs["position_actual_value"].astype(np.float64)
        g.gate.claim(dp.guid.hex, "test")  # the server knows a client by its DDS participant, not a string
        commands.write(m.JointCommand(client_id="test", sequence=1, position=(start + OFFSETS).tolist()))
        _run_until(emu, server, lambda: g.gate.applied_sequence == 1, 2000)
        assert g.gate.applied_sequence == 1
        assert not g.gate.latched
        emu.run(server.step, cycles=500)  # the axes move to their targets

        states.take(N=64)
        axis_states.take(N=64)  # what came before the move
        got: list[m.JointState] = []
        got_st: list[m.AxisState] = []

        def both() -> bool:
            got.extend(s for s in states.take(N=8) if isinstance(s, m.JointState))
            got_st.extend(s for s in axis_states.take(N=8) if isinstance(s, m.AxisState))
            return bool(got and got_st)

        _run_until(emu, server, both, 2000)
        assert got and got_st, "no JointState / AxisState came over DDS"
        js = got[-1]
        assert list(js.name) == JOINTS  # two joints per slave
        np.testing.assert_allclose(js.position, start + OFFSETS, atol=20)
        assert got_st[-1].fresh == [True] * 4  # freshness per joint

        # an SDO request for joint shoulder.axis2 reads axis 2's position (0x6064 -> 0x6864)
        names = service_names("arm")
        requests = DataWriter(dp, Topic(dp, names["request"], m.Request), qos=RELIABLE)
        replies = DataReader(dp, Topic(dp, names["reply"], m.Reply), qos=RELIABLE)
        arg = json.dumps({"axis": "shoulder.axis2", "index": 0x6064, "sub_index": 0})
        requests.write(m.Request(client_id="test", request_id=7, group=name, verb="sdo_read", argument=arg))
        answers: list[m.Reply] = []
        _run_until(
            emu,
            server,
            lambda: answers.extend(r for r in replies.take(N=8) if r.request_id == 7) or answers,
            2000,
        )
        assert answers and answers[-1].ok, answers
        actual = int.from_bytes(bytes.fromhex(json.loads(answers[-1].detail)["data"]), "little", signed=True)
        rows = emu.op[name].inputs["position_actual_value"]
        assert abs(actual - rows[1]) <= 20 < abs(actual - rows[0])  # axis 2's, not axis 1's
        assert not g.gate.latched
