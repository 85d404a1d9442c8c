"""The served bus's safety contract, adversarially, in process on a virtual clock.

``fieldbus serve``'s cycle (:class:`BusServer.step`) runs on the sim emulator
(``fieldbus.testing.emulate``); every client is a DDS participant of its own in
this process, made with cyclonedds alone (plain writers and readers of the
wire types), so the server knows it only as DDS tells it. Local delivery in
Cyclone DDS is synchronous: a sample written before a cycle is taken in that
cycle, so every bound here is in cycles.

docs/safety.md ("The served bus") names each test next to its invariant.
"""

from __future__ import annotations

import gc
import json
import math
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("cyclonedds")

from cyclonedds.domain import DomainParticipant
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic

import fieldbus
from fieldbus.dds import cdr
from fieldbus.dds import messages as m
from fieldbus.dds.gate import Deadline, GateState
from fieldbus.dds.participant import REALTIME, RELIABLE, Participant
from fieldbus.dds.server import BusServer, ServeOptions
from fieldbus.testing import emulate

DEMO_JOINT = Path(fieldbus.__file__).resolve().parent / "data" / "demo_joint.yaml"
HOLD, STOP = 20, 200
ENABLED = int(fieldbus.State402.OPERATION_ENABLED)
DOMAIN = 1 + (os.getpid() * 13) % 200  # this test run's own: other runs on the machine use others


def _csv_map(tmp_path: Path) -> Path:
    """The demo joint in cyclic synchronous velocity (CSV): target velocity 0x60FF mapped, mode 9."""
    text = DEMO_JOINT.read_text().replace('value: 8, description: "modes of operation: CSP"', "value: 9")
    text = text.replace(
        "      - {index: 0x6060, sub_index: 0, type: int8, default: 8}",
        "      - {index: 0x6060, sub_index: 0, type: int8, default: 9}\n"
        "      - {index: 0x60FF, sub_index: 0, type: int32, factor: 20860.7568, unit: rad/s}",
    )
    path = tmp_path / "csv_joint.yaml"
    path.write_text(text)
    return path


def _net(tmp_path: Path, drive_map: Path = DEMO_JOINT) -> Path:
    net = tmp_path / "robot.yaml"
    net.write_text(
        "name: robot\ncycle_time_us: 1000\nreceive_timeout_us: 500\nbuses:\n  - name: bus\n    type: ethercat\n"
        f"    interface: sim\n    slaves: [{{name: 'j{{i}}', map: {json.dumps(str(drive_map))}, count: 3}}]\n"
    )
    return net


class Served:
    """The served cycle, stepped by the test: ``cycles(n)`` runs n bus cycles on the virtual clock."""

    def __init__(self, emu: Any, server: BusServer) -> None:
        self.emu, self.server = emu, server
        self.group = next(iter(server.groups))
        self.g = server.groups[self.group]
        self._k = 0

    def cycles(self, n: int) -> None:
        base = self._k
        self._k += n

        def step(k: int) -> None:
            self.server.step(base + k)

        self.emu.run(step, n)

    @property
    def states(self) -> list[int]:
        return self.g.ctrl.state.tolist() if self.g.ctrl is not None else []

    def actual(self, channel: str) -> np.ndarray[Any, Any]:
        return np.asarray(self.g.image.inputs.values[channel], dtype=float).copy()


@pytest.fixture
def served(tmp_path: Path, request: pytest.FixtureRequest) -> Iterator[Served]:
    drive_map = _csv_map(tmp_path) if "csv" in request.node.name else DEMO_JOINT
    with emulate(_net(tmp_path, drive_map), bring_up=False) as emu:
        server = BusServer(
            emu.network,
            Participant(DOMAIN, "lo"),
            ServeOptions("robot", deadline=Deadline(HOLD, STOP), diagnostics_every=10**9),
        )
        server.attach(emu.bring_up())
        s = Served(emu, server)
        s.cycles(20)
        yield s


class Client:
    """A client with a DDS participant of its own and cyclonedds only: the wire types, its own writers."""

    def __init__(self, s: Served, client_id: str) -> None:
        self.s, self.client_id = s, client_id
        dp = self.dp = DomainParticipant(DOMAIN)
        self.requests = DataWriter(dp, Topic(dp, "rt/robot/request", m.Request), qos=RELIABLE)
        self.replies = DataReader(dp, Topic(dp, "rt/robot/reply", m.Reply), qos=RELIABLE)
        self.commands = DataWriter(dp, Topic(dp, f"rt/robot/{s.group}/command", m.JointCommand), qos=REALTIME)
        self.request_id = 0
        self.sequence = 0

    def ask(self, verb: str, argument: dict[str, Any] | None = None, *, within: int = 3000) -> m.Reply:
        """Send a request; the server's reply within ``within`` cycles."""
        self.request_id += 1
        self.requests.write(
            m.Request(
                client_id=self.client_id,
                request_id=self.request_id,
                group=self.s.group,
                verb=verb,
                argument=json.dumps(argument) if argument else "",
            )
        )
        for _ in range(within):
            self.s.cycles(1)
            for r in self.replies.take(N=8):
                if (
                    isinstance(r, m.Reply)
                    and r.client_id == self.client_id
                    and r.request_id == self.request_id
                ):
                    return r
        pytest.fail(f"no reply to {verb} within {within} cycles")

    def must(self, verb: str, argument: dict[str, Any] | None = None) -> m.Reply:
        r = self.ask(verb, argument)
        assert r.ok, r.error
        return r

    def command(self, *, client_id: str | None = None, sequence: int | None = None, **fields: Any) -> None:
        self.sequence = self.sequence + 1 if sequence is None else sequence
        self.commands.write(
            m.JointCommand(client_id=client_id or self.client_id, sequence=self.sequence, **fields)
        )

    def close(self) -> None:
        """The process ends: its participant leaves the domain (its writers are unmatched at once)."""
        self.dp = None  # type: ignore[assignment]
        self.requests = self.replies = self.commands = None  # type: ignore[assignment]
        gc.collect()


def _enabled(s: Served, a: Client) -> None:
    """``a`` claims and enables; the drives OPERATION ENABLED (the reply says so; at most 3000 cycles)."""
    a.must("claim")
    a.must("enable")
    for _ in range(3000):
        if s.states == [ENABLED] * 3:
            return
        s.cycles(1)
    pytest.fail(f"not enabled: {s.states}")


# -- item 10: commands only from the claiming participant ---------------------------------------------------


def test_a_forged_client_id_with_a_higher_sequence_is_refused_and_the_owner_keeps_commanding(
    served: Served,
) -> None:
    s = served
    owner, forger = Client(s, "owner"), Client(s, "forger")
    _enabled(s, owner)
    start = s.actual("position_actual_value")
    hold = start.tolist()
    forged = (start + 0.06).tolist()
    for k in range(300):
        owner.command(position=hold)
        forger.command(client_id="owner", sequence=10_000 + k, position=forged)  # the owner's string
        s.cycles(1)
    assert s.g.gate.applied_sequence == owner.sequence  # the owner's commands, none dropped as stale
    assert s.g.refusals["not_owner"] == 300 and s.g.gate.dropped == 0
    assert np.allclose(s.actual("position_actual_value"), start, atol=1e-3)  # not moved by the forger
    assert s.g.gate.state is GateState.COMMANDED
    # and its requests are not the owner's either
    assert not forger.ask("clear_safe_stop").ok and not Client(s, "owner").ask("release").ok


# -- item 3: NaN and inf refused with the reason, never liveness ---------------------------------------------


def test_inf_in_one_position_is_refused_and_does_not_move_the_joint(served: Served) -> None:
    s = served
    a = Client(s, "a")
    _enabled(s, a)
    start = s.actual("position_actual_value")
    a.command(position=start.tolist())
    s.cycles(5)
    bad = start.tolist()
    bad[1] = math.inf
    for _ in range(100):
        a.command(position=bad)
        s.cycles(1)
    assert np.allclose(s.actual("position_actual_value"), start, atol=1e-3)
    assert s.g.refusals["not_finite"] == 100
    values = {kv.key: kv.value for st in s.server.diagnostics().status for kv in st.values}
    assert values["refused/not_finite"] == "100" and "NaN or infinite" in values["last_refusal"]


def test_nan_commands_do_not_keep_a_dead_controller_alive_hold_then_safe_stop_in_cycles(
    served: Served,
) -> None:
    s = served
    a = Client(s, "a")
    _enabled(s, a)
    a.command(position=s.actual("position_actual_value").tolist())
    s.cycles(1)
    assert s.g.gate.state is GateState.COMMANDED
    nan = [math.nan] * 3
    seen = []
    for _ in range(STOP + 10):
        a.command(position=nan)
        s.cycles(1)
        seen.append(s.g.gate.state)
    assert seen[HOLD - 1] is GateState.HOLD and seen[STOP - 1] is GateState.SAFE_STOP
    assert all(st != ENABLED for st in s.states)  # the latch took the drives out of OPERATION ENABLED
    assert s.g.refusals["not_finite"] == STOP + 10


def test_wrong_length_is_refused_with_its_own_reason(served: Served) -> None:
    s = served
    a = Client(s, "a")
    a.must("claim")
    a.command(position=[0.0, 0.0])
    s.cycles(1)
    assert s.g.refusals == {"wrong_length": 1, "not_finite": 0, "not_owner": 0, "before_transition": 0}
    assert "want 0 or 3" in s.g.last_refusal


# -- item 11: a claim held by a client that never commands -------------------------------------------------


def test_a_client_killed_after_enable_before_its_first_command_frees_the_group_within_the_deadline(
    served: Served,
) -> None:
    s = served
    a = Client(s, "a")
    _enabled(s, a)
    s.cycles(STOP - 2)  # the deadline counts from the cycle that answered the enable
    assert s.g.gate.state is GateState.IDLE  # not fired yet
    s.cycles(1)
    assert s.g.gate.state is GateState.SAFE_STOP and "no command" in s.g.latched_by
    s.cycles(20)
    assert all(st != ENABLED for st in s.states)
    b = Client(s, "b")
    b.must("claim")  # claimable again
    b.must("clear_safe_stop")
    assert s.g.gate.owner is not None and s.g.gate.label == "b"


def test_a_client_whose_participant_leaves_frees_the_group(served: Served) -> None:
    s = served
    a = Client(s, "a")
    _enabled(s, a)
    a.command(position=s.actual("position_actual_value").tolist())
    s.cycles(2)
    a.close()
    s.cycles(20)  # well within the deadline: the owner's writers were unmatched
    assert s.g.gate.state is GateState.SAFE_STOP and "left the DDS domain" in s.g.latched_by
    Client(s, "b").must("claim")


# -- items 4 and 5: no transition starts motion ------------------------------------------------------------


def test_csv_after_the_bus_safe_stop_a_clear_alone_does_not_enable_or_move(served: Served) -> None:
    s = served
    a = Client(s, "a")
    _enabled(s, a)
    for _ in range(200):
        a.command(velocity=[8.0, 8.0, 8.0])
        s.cycles(1)
    assert (s.actual("velocity_actual_value") > 4.0).all()
    s.emu.lose_cycles("bus", 15)  # the bus's own safe stop: 15 lost frames
    for _ in range(40):
        a.command(velocity=[8.0, 8.0, 8.0])
        s.cycles(1)
    assert s.server.op.result.safe_stop and s.g.gate.latched
    a.must("clear_safe_stop")
    s.cycles(300)
    assert all(st != ENABLED for st in s.states)  # the goal stayed DISABLE: no enable came
    assert (s.g.image.outputs.values["target_velocity"] == 0).all()  # and the old 8 rad/s is gone
    assert (s.actual("velocity_actual_value") < 2.0).all()  # coasting down, not driven


def test_csv_a_new_owner_that_enables_without_commanding_does_not_run_the_old_velocity(
    served: Served,
) -> None:
    s = served
    a = Client(s, "a")
    _enabled(s, a)
    for _ in range(200):
        a.command(velocity=[8.0, 8.0, 8.0])
        s.cycles(1)
    a.close()  # A dies; its deadline (or its departure) latches
    s.cycles(STOP + 20)
    assert s.g.gate.latched
    b = Client(s, "b")
    b.must("claim")
    b.must("clear_safe_stop")
    b.must("enable")
    s.cycles(STOP // 2)  # within b's no-command deadline
    assert s.states == [ENABLED] * 3
    assert np.allclose(s.actual("velocity_actual_value"), 0.0, atol=0.05)  # enabling did not move a joint
    assert (s.g.image.outputs.values["target_velocity"] == 0).all()


def test_commands_sent_before_an_enable_are_not_applied_after_it(served: Served) -> None:
    s = served
    a = Client(s, "a")
    a.must("claim")
    start = s.actual("position_actual_value")
    a.command(position=(start + 0.05).tolist())  # sent before the enable, taken with it
    a.must("enable")
    s.cycles(100)
    assert np.allclose(s.actual("position_actual_value"), start, atol=1e-3)
    assert s.g.refusals["before_transition"] >= 1


# -- item 12: recovery after faults -------------------------------------------------------------------------


def test_claim_clear_enable_recovers_after_a_bus_safe_stop_that_faulted_every_drive(served: Served) -> None:
    s = served
    a = Client(s, "a")
    _enabled(s, a)
    a.command(position=s.actual("position_actual_value").tolist())
    s.cycles(1)
    s.emu.lose_cycles("bus", 15)
    s.cycles(20)
    assert s.server.op.result.safe_stop
    for j in ("j0", "j1", "j2"):
        s.emu.drive_fault("bus", j, 0x8100)
    s.cycles(3000)  # a long latch: no fault reset is spent against the safe outputs
    assert s.states == [int(fieldbus.State402.FAULT)] * 3
    assert (s.g.ctrl.fault_resets == 0).all()
    b = Client(s, "b")
    b.must("claim")
    b.must("clear_safe_stop")
    b.must("enable")
    assert s.states == [ENABLED] * 3


def test_reset_faults_re_arms_a_drive_that_spent_its_fault_reset_budget(served: Served) -> None:
    s = served
    a = Client(s, "a")
    _enabled(s, a)
    ctrl = s.g.ctrl
    ctrl.gave_up[1] = True  # j1 spent its budget (what bounded automatic resets leave behind)
    s.emu.drive_fault("bus", "j1", 0x7300)
    s.cycles(50)
    assert (
        s.g.gate.latched and "drive fault" in s.g.latched_by and s.states[1] == int(fieldbus.State402.FAULT)
    )
    a.must("clear_safe_stop")
    ctrl.gave_up[1] = True
    r = a.must("reset_faults", {"axis": "j1"})
    assert json.loads(r.detail) == {"re_armed": ["j1"]}
    a.must("enable")
    assert s.states == [ENABLED] * 3


# -- item 13: unique diagnostic names ----------------------------------------------------------------------


def test_every_diagnostic_status_has_its_own_name(served: Served) -> None:
    names = [st.name for st in served.server.diagnostics().status]
    assert len(names) == len(set(names)) and "fieldbus/bus/bus" in names and "fieldbus/group/bus" in names


# -- issue 36: a remote command costs one cycle ---------------------------------------------------------------


def test_a_command_taken_before_a_cycle_is_applied_and_shown_in_that_same_cycle(served: Served) -> None:
    """Written before cycle k starts: taken by k, on the wire in k's exchange, and the state published
    right after k's exchange names it (command_sequence) with k's cycle number; never one cycle later."""
    s = served
    a = Client(s, "controller")
    states = DataReader(a.dp, Topic(a.dp, f"rt/robot/{s.group}/axis_state", m.AxisState), qos=REALTIME)
    _enabled(s, a)
    hold = s.actual("position_actual_value").tolist()
    sent_before = s.emu.op.result.cycle
    for _ in range(50):
        a.command(position=hold)
        cycle_before = s.emu.op.result.cycle
        s.cycles(1)
        shown = [st for st in states.take(N=16) if isinstance(st, m.AxisState)]
        assert shown, "no state published in the cycle"
        newest = shown[-1]
        assert newest.command_sequence == a.sequence  # applied in this very cycle
        assert newest.cycle == cycle_before + 1 == s.emu.op.result.cycle
    assert s.emu.op.result.cycle == sent_before + 50


def _command_and_read_back(s: Served, counted: list[str] | None = None) -> None:
    """A cyclonedds-only client commands a small step for 200 cycles; its own deserializer (the oracle)
    then reads the newest JointState and AxisState: the image's values bit for bit. ``counted``: the
    names of cyclonedds (de)serializer calls the server made in those cycles (the test patches them)."""
    a = Client(s, "controller")
    states = DataReader(a.dp, Topic(a.dp, f"rt/robot/{s.group}/axis_state", m.AxisState), qos=REALTIME)
    joints = DataReader(a.dp, Topic(a.dp, f"rt/robot/{s.group}/joint_states", m.JointState), qos=REALTIME)
    _enabled(s, a)
    target = s.actual("position_actual_value") + 0.01  # a small step, so the published positions move
    for _ in range(200):
        a.command(position=target.tolist())  # the client's own write
        if counted is not None:
            counted.clear()  # (counted, then cleared)
        s.cycles(1)
        assert not counted, f"the served step used cyclonedds's serializer: {counted}"
    js = [x for x in joints.take(N=16) if isinstance(x, m.JointState)][-1]
    st = [x for x in states.take(N=16) if isinstance(x, m.AxisState)][-1]
    assert js.name == list(s.g.axes)
    assert js.position == s.actual("position_actual_value").tolist()  # the image's newest, bit for bit
    assert np.allclose(js.position, target, atol=2e-3)  # and the command reached the drives
    assert st.command_sequence == a.sequence and st.cycle == s.emu.op.result.cycle and st.all_fresh
    assert st.owner == "controller" and st.drive_state == [ENABLED] * 3


def test_the_served_step_encodes_and_decodes_its_messages_itself_and_a_cyclonedds_client_reads_them(
    served: Served, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Issue 33's step budget: in commanded cycles the server calls none of cyclonedds's Python
    (de)serializer for the command, JointState or AxisState (0.05-0.14 ms each on the reference VM);
    the client, cyclonedds only, reads what the image holds (its own deserializer is the oracle)."""
    calls: list[str] = []
    for cls in (m.JointCommand, m.JointState, m.AxisState):
        idl = cls.__idl__
        for name in ("serialize", "deserialize"):
            real = getattr(idl, name)
            monkeypatch.setattr(idl, name, lambda *a_, _r=real, _n=f"{cls.__name__}.{name}", **k: (calls.append(_n), _r(*a_, **k))[1])  # fmt: skip
    _command_and_read_back(served, calls)


def test_where_bytes_cannot_be_handed_to_cyclonedds_the_server_publishes_through_its_serializer(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Another cyclonedds binding without the C write call: every writer falls back to cyclonedds's own
    serializer, and the client reads the same values as from the encoded messages."""
    monkeypatch.setattr(cdr, "ddspy_write", None)
    with emulate(_net(tmp_path, DEMO_JOINT), bring_up=False) as emu:
        server = BusServer(
            emu.network, Participant(DOMAIN, "lo"), ServeOptions("robot", diagnostics_every=10**9)
        )
        server.attach(emu.bring_up())
        s = Served(emu, server)
        assert not s.g.js_writer.fast and s.g._js_bytes is None and s.g._st_bytes is None
        s.cycles(20)
        _command_and_read_back(s)
