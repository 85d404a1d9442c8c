"""The messages on the wire, as Cyclone DDS IDL types named the way rmw_cyclonedds names ROS 2 types.

ROS 2 types (a ROS 2 node on rmw_cyclonedds reads them with no bridge): the
type name is ``<package>::msg::dds_::<Type>_`` and the fields are those of the
``.msg`` file, sequences unbounded (``sensor_msgs/msg/JointState``,
``std_msgs/msg/Header``, ``builtin_interfaces/msg/Time``,
``diagnostic_msgs/msg/DiagnosticArray``). The fieldbus messages follow the same
convention in the package ``fieldbus_msgs``: what JointState cannot carry
(:class:`AxisState`), the command (:class:`JointCommand`) and the requests
(:class:`Request` answered by :class:`Reply`).

Units: positions in rad (or m), velocities per second, efforts in N·m (or N),
as the drive map scales them; times in ns since the Unix epoch.
"""

# no ``from __future__ import annotations``: cyclonedds resolves the annotations at run time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from cyclonedds.idl import IdlStruct
from cyclonedds.idl import types as t
from cyclonedds.idl.annotations import key

if TYPE_CHECKING:
    Seq = list  # what a reader sees: a list
else:
    Seq = t.sequence  # what cyclonedds reads: an unbounded IDL sequence


@dataclass
class Time(IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):
    """builtin_interfaces/Time: seconds and nanoseconds."""

    sec: t.int32 = 0
    nanosec: t.uint32 = 0

    @classmethod
    def of_ns(cls, ns: int) -> "Time":
        """A stamp from nanoseconds since the Unix epoch."""
        return cls(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


@dataclass
class Header(IdlStruct, typename="std_msgs::msg::dds_::Header_"):
    """std_msgs/Header: a stamp and a frame id."""

    stamp: Time = field(default_factory=Time)
    frame_id: str = ""


@dataclass
class JointState(IdlStruct, typename="sensor_msgs::msg::dds_::JointState_"):
    """sensor_msgs/JointState: one entry per joint, positions/velocities/efforts in SI units."""

    header: Header = field(default_factory=Header)
    name: Seq[str] = field(default_factory=list)
    position: Seq[t.float64] = field(default_factory=list)
    velocity: Seq[t.float64] = field(default_factory=list)
    effort: Seq[t.float64] = field(default_factory=list)


@dataclass
class KeyValue(IdlStruct, typename="diagnostic_msgs::msg::dds_::KeyValue_"):
    """diagnostic_msgs/KeyValue."""

    key: str = ""
    value: str = ""


@dataclass
class DiagnosticStatus(IdlStruct, typename="diagnostic_msgs::msg::dds_::DiagnosticStatus_"):
    """diagnostic_msgs/DiagnosticStatus; ``level``: 0 OK, 1 WARN, 2 ERROR, 3 STALE."""

    level: t.uint8 = 0
    name: str = ""
    message: str = ""
    hardware_id: str = ""
    values: Seq[KeyValue] = field(default_factory=list)


@dataclass
class DiagnosticArray(IdlStruct, typename="diagnostic_msgs::msg::dds_::DiagnosticArray_"):
    """diagnostic_msgs/DiagnosticArray: one status per bus and per axis group."""

    header: Header = field(default_factory=Header)
    status: Seq[DiagnosticStatus] = field(default_factory=list)


@dataclass
class AxisState(IdlStruct, typename="fieldbus_msgs::msg::dds_::AxisState_"):
    """What JointState cannot carry, published with it (same cycle).

    ``fresh`` per axis: its inputs were decoded this cycle. ``drive_state`` per
    axis: the CiA 402 state code (:class:`fieldbus.State402`, -1 unknown or not
    a CiA 402 drive). ``inputs``: every input channel of every axis, row-major
    (axis, channel) in the order the describe reply names them, as float64.
    ``command_sequence``: the newest command applied (0: none);
    ``command_age``: cycles since the newest accepted command. ``gate``: 0 idle
    (no command yet), 1 commanded, 2 hold (deadline missed), 3 safe stop
    (latched). ``cycle``: the bus's cycle number after this cycle's exchange.
    """

    header: Header = field(default_factory=Header)
    cycle: t.uint64 = 0
    fresh: Seq[bool] = field(default_factory=list)
    drive_state: Seq[t.int8] = field(default_factory=list)
    inputs: Seq[t.float64] = field(default_factory=list)
    all_fresh: bool = False
    safe_stop: bool = False
    gate: t.uint8 = 0
    command_sequence: t.uint64 = 0
    command_age: t.uint32 = 0
    owner: str = ""
    dropped_sequences: t.uint32 = 0  # commands whose sequence number did not increase
    refused_commands: t.uint32 = 0  # not from the owner's participant, wrong length, or NaN/inf


@dataclass
class JointCommand(IdlStruct, typename="fieldbus_msgs::msg::dds_::JointCommand_"):
    """A command for one axis group: per joint, whatever the group's drives accept.

    An empty sequence leaves that quantity as it was; a non-empty one has one
    entry per axis, every value finite. ``client_id``: the sender's name (the
    server trusts the writer's DDS participant, not this string).
    ``sequence``: strictly increasing per claim (a lower or equal one is dropped).
    Units: rad, rad/s, N·m, N·m/rad, N·m·s/rad (as the drive map scales them).
    """

    header: Header = field(default_factory=Header)
    client_id: str = ""
    key("client_id")  # one instance per client_id (the server's reader keeps 8 samples per instance)
    sequence: t.uint64 = 0
    position: Seq[t.float64] = field(default_factory=list)
    velocity: Seq[t.float64] = field(default_factory=list)
    torque: Seq[t.float64] = field(default_factory=list)
    kp: Seq[t.float64] = field(default_factory=list)
    kd: Seq[t.float64] = field(default_factory=list)


@dataclass
class Request(IdlStruct, typename="fieldbus_msgs::msg::dds_::Request_"):
    """A request to the served bus: ``verb`` is one of :data:`fieldbus.dds.gate.VERBS`.

    ``group``: the axis group it is for ("" for ``describe``). ``request_id``:
    chosen by the client, echoed in the reply.
    """

    client_id: str = ""
    request_id: t.uint32 = 0
    group: str = ""
    verb: str = ""
    argument: str = ""


@dataclass
class Reply(IdlStruct, typename="fieldbus_msgs::msg::dds_::Reply_"):
    """The answer to a :class:`Request`: ``ok`` and, if not, the error; ``detail``: a JSON text or ""."""

    client_id: str = ""
    request_id: t.uint32 = 0
    ok: bool = False
    error: str = ""
    detail: str = ""
