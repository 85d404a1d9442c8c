"""ros2_control without C++: the layout of ros-controls' topic_based_hardware_interfaces.

Its ``joint_state_topic_hardware_interface/JointStateTopicSystem`` publishes every command as a
``sensor_msgs/JointState`` on ``joint_commands_topic`` (default ``/robot_joint_commands``): ``name`` lists
the joints, and ``position`` / ``velocity`` / ``effort`` each carry one value per joint for the joints
whose URDF block has that command interface (the field is empty otherwise). It reads the robot's state
as a ``JointState`` on ``joint_states_topic`` (default ``/robot_joint_states``). :class:`TopicControl`
is the other end of those two topics: an unmodified controller_manager with that hardware interface
drives the served joints.

The served bus's rules hold (:mod:`fieldbus.dds.topic_claim`): the first participant whose command is
valid takes the groups its joints are in and enables them; until they are enabled the targets follow
the joints; another participant, a NaN or infinite value, a field whose length is neither 0 nor the
number of names, and a joint that is not served are refused (counted per reason, never liveness); the
groups' deadline applies (a controller_manager that stops writing holds, then latches the safe stop).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

from cyclonedds.topic import Topic

from fieldbus.dds import messages as m
from fieldbus.dds.cdr import PlainReader, PlainWriter
from fieldbus.dds.participant import COMMANDS, REALTIME
from fieldbus.dds.topic_claim import TopicClaim

if TYPE_CHECKING:
    from fieldbus.dds.parts import BusServer, ServedGroup

DEFAULT_COMMANDS, DEFAULT_STATES = "/robot_joint_commands", "/robot_joint_states"
REASONS = ("not_finite", "wrong_length", "unknown_joint", "not_owner", "groups_claimed")
FIELDS = {"position": "position", "velocity": "velocity", "effort": "torque"}  # JointState -> command role


def dds_topic(ros_name: str) -> str:
    """A ROS 2 topic name as rmw_cyclonedds writes it (``/robot_joint_commands`` -> ``rt/robot_joint_commands``)."""
    return "rt/" + ros_name.strip("/")


class TopicControl:
    """The two topics of a topic-based ros2_control hardware interface, on ``server``'s groups."""

    def __init__(
        self,
        server: BusServer,
        commands_topic: str = DEFAULT_COMMANDS,
        states_topic: str = DEFAULT_STATES,
        exclude: tuple[str, ...] = (),
    ) -> None:
        self.server = server
        dp = server.participant.dp
        self.topics = {"commands": dds_topic(commands_topic), "states": dds_topic(states_topic)}
        self.reader = PlainReader(dp, Topic(dp, self.topics["commands"], m.JointState), qos=COMMANDS)
        self.writer = PlainWriter(dp, Topic(dp, self.topics["states"], m.JointState), qos=REALTIME)
        # every served joint (except the base's wheels) -> (its group, its row)
        self.joints: dict[str, tuple[ServedGroup, int]] = {
            axis: (g, i)
            for g in server.groups.values()
            if g.name not in exclude
            for i, axis in enumerate(g.axes)
        }
        self.claim = TopicClaim("joint_commands", server.callers)
        self.refusals = dict.fromkeys(REASONS, 0)
        self.last_refusal = ""
        self.applied = 0

    def _refuse(self, reason: str, why: str) -> None:
        self.refusals[reason] += 1
        self.last_refusal = why

    def take(self) -> None:
        """The newest valid command of this cycle, applied to the joints it names (before the gates tick)."""
        why = self.claim.lost()
        if why is not None:
            self.claim.let_go()
        newest: tuple[m.JointState, list[tuple[ServedGroup, int]]] | None = None
        for cmd in self.reader.take(N=32):
            if not isinstance(cmd, m.JointState):
                continue
            rows = self._check(cmd)
            if rows is None:
                continue
            who = self.claim.who(self.reader, cmd)
            if who is None:
                self._refuse("not_owner", "a command from a DDS participant not known yet")
                continue
            if self.claim.owner is None:
                groups = list({id(g): g for g, _ in rows}.values())
                busy = self.claim.busy(groups)
                if busy is not None:
                    self._refuse("groups_claimed", f"group '{busy.name}' is claimed by '{busy.gate.label}'")
                    continue
                self.claim.take(who, groups)
            if who != self.claim.owner:
                self._refuse("not_owner", f"a command from DDS participant {who}, not the owner's")
                continue
            if any(g not in self.claim.groups for g, _ in rows):
                self._refuse("groups_claimed", "a command for joints outside the groups first taken")
                continue
            self.claim.seen(self.reader, cmd)
            newest = (cmd, rows)
        if newest is None or not self.claim.enabled:
            return  # enabling: a command taken before the drives are enabled does not apply
        cmd, rows = newest
        for field, role in FIELDS.items():
            values = getattr(cmd, field)
            if not values:
                continue
            for (g, row), v in zip(rows, values, strict=True):
                chan = g.out_roles.get(role)
                if chan is not None:
                    g.image.outputs.values[chan][row] = v
        self.claim.offer()
        self.applied += 1

    def _check(self, cmd: m.JointState) -> list[tuple[ServedGroup, int]] | None:
        """The rows ``cmd`` names, or None (refused, with the reason counted)."""
        n = len(cmd.name)
        for field in FIELDS:
            if len(getattr(cmd, field)) not in (0, n):
                self._refuse("wrong_length", f"{field} has {len(getattr(cmd, field))} values for {n} names")
                return None
            if not all(math.isfinite(v) for v in getattr(cmd, field)):
                self._refuse("not_finite", f"a {field} value is NaN or infinite")
                return None
        rows = []
        for name in cmd.name:
            where = self.joints.get(name)
            if where is None:
                self._refuse("unknown_joint", f"no served joint '{name}'")
                return None
            rows.append(where)
        return rows or None

    def publish(self, stamp_ns: int) -> None:
        """Every served joint's state: positions, velocities and efforts as the groups' JointState has them."""
        msg = m.JointState(header=m.Header(stamp=m.Time.of_ns(stamp_ns)))
        for name, (g, row) in self.joints.items():
            inp = g.image.inputs.values
            msg.name.append(name)
            for field, attr in (("position", "position"), ("velocity", "velocity"), ("effort", "effort")):
                chan = g.in_roles.get(attr)
                getattr(msg, field).append(float(inp[chan][row]) if chan is not None else math.nan)
        self.writer.write(msg)

    def describe(self) -> dict[str, Any]:
        return {"topics": self.topics, "joints": list(self.joints)}
