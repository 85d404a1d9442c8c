"""A ROS 2-style client of a wheeled base, written with cyclonedds and the standard ROS 2 message
definitions only (no fieldbus import): the ``.msg`` files of builtin_interfaces, std_msgs, geometry_msgs,
nav_msgs, tf2_msgs, sensor_msgs and diagnostic_msgs, as rmw_cyclonedds names them on the wire.

``BaseClient(domain, namespace="")`` publishes ``cmd_vel`` (Twist, or TwistStamped with ``stamped=True``)
and reads ``odom``, ``tf``, ``joint_states`` and ``diagnostics``, as Nav2 and tf2 would.
"""

from dataclasses import dataclass, field

from cyclonedds.core import Policy, Qos
from cyclonedds.domain import DomainParticipant
from cyclonedds.idl import IdlStruct
from cyclonedds.idl import types as t
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration


@dataclass
class Time_(IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):
    sec: t.int32 = 0
    nanosec: t.uint32 = 0


@dataclass
class Header_(IdlStruct, typename="std_msgs::msg::dds_::Header_"):
    stamp: Time_ = field(default_factory=Time_)
    frame_id: str = ""


@dataclass
class Vector3_(IdlStruct, typename="geometry_msgs::msg::dds_::Vector3_"):
    x: t.float64 = 0.0
    y: t.float64 = 0.0
    z: t.float64 = 0.0


@dataclass
class Twist_(IdlStruct, typename="geometry_msgs::msg::dds_::Twist_"):
    linear: Vector3_ = field(default_factory=Vector3_)
    angular: Vector3_ = field(default_factory=Vector3_)


@dataclass
class TwistStamped_(IdlStruct, typename="geometry_msgs::msg::dds_::TwistStamped_"):
    header: Header_ = field(default_factory=Header_)
    twist: Twist_ = field(default_factory=Twist_)


@dataclass
class Point_(IdlStruct, typename="geometry_msgs::msg::dds_::Point_"):
    x: t.float64 = 0.0
    y: t.float64 = 0.0
    z: t.float64 = 0.0


@dataclass
class Quaternion_(IdlStruct, typename="geometry_msgs::msg::dds_::Quaternion_"):
    x: t.float64 = 0.0
    y: t.float64 = 0.0
    z: t.float64 = 0.0
    w: t.float64 = 1.0


@dataclass
class Pose_(IdlStruct, typename="geometry_msgs::msg::dds_::Pose_"):
    position: Point_ = field(default_factory=Point_)
    orientation: Quaternion_ = field(default_factory=Quaternion_)


@dataclass
class PoseWithCovariance_(IdlStruct, typename="geometry_msgs::msg::dds_::PoseWithCovariance_"):
    pose: Pose_ = field(default_factory=Pose_)
    covariance: t.array[t.float64, 36] = field(default_factory=lambda: [0.0] * 36)


@dataclass
class TwistWithCovariance_(IdlStruct, typename="geometry_msgs::msg::dds_::TwistWithCovariance_"):
    twist: Twist_ = field(default_factory=Twist_)
    covariance: t.array[t.float64, 36] = field(default_factory=lambda: [0.0] * 36)


@dataclass
class Odometry_(IdlStruct, typename="nav_msgs::msg::dds_::Odometry_"):
    header: Header_ = field(default_factory=Header_)
    child_frame_id: str = ""
    pose: PoseWithCovariance_ = field(default_factory=PoseWithCovariance_)
    twist: TwistWithCovariance_ = field(default_factory=TwistWithCovariance_)


@dataclass
class Transform_(IdlStruct, typename="geometry_msgs::msg::dds_::Transform_"):
    translation: Vector3_ = field(default_factory=Vector3_)
    rotation: Quaternion_ = field(default_factory=Quaternion_)


@dataclass
class TransformStamped_(IdlStruct, typename="geometry_msgs::msg::dds_::TransformStamped_"):
    header: Header_ = field(default_factory=Header_)
    child_frame_id: str = ""
    transform: Transform_ = field(default_factory=Transform_)


@dataclass
class TFMessage_(IdlStruct, typename="tf2_msgs::msg::dds_::TFMessage_"):
    transforms: t.sequence[TransformStamped_] = field(default_factory=list)


@dataclass
class JointState_(IdlStruct, typename="sensor_msgs::msg::dds_::JointState_"):
    header: Header_ = field(default_factory=Header_)
    name: t.sequence[str] = field(default_factory=list)
    position: t.sequence[t.float64] = field(default_factory=list)
    velocity: t.sequence[t.float64] = field(default_factory=list)
    effort: t.sequence[t.float64] = field(default_factory=list)


@dataclass
class KeyValue_(IdlStruct, typename="diagnostic_msgs::msg::dds_::KeyValue_"):
    key: str = ""
    value: str = ""


@dataclass
class DiagnosticStatus_(IdlStruct, typename="diagnostic_msgs::msg::dds_::DiagnosticStatus_"):
    level: t.uint8 = 0
    name: str = ""
    message: str = ""
    hardware_id: str = ""
    values: t.sequence[KeyValue_] = field(default_factory=list)


@dataclass
class DiagnosticArray_(IdlStruct, typename="diagnostic_msgs::msg::dds_::DiagnosticArray_"):
    header: Header_ = field(default_factory=Header_)
    status: t.sequence[DiagnosticStatus_] = field(default_factory=list)


# rclcpp's defaults: SystemDefaultsQoS (reliable, keep last) for cmd_vel, odom and tf
RELIABLE = Qos(Policy.Reliability.Reliable(duration(seconds=1)), Policy.History.KeepLast(10))


class BaseClient:
    """One ROS 2 node's worth of DDS: a participant of its own, cmd_vel out, odom/tf/diagnostics in."""

    def __init__(self, domain: int, namespace: str = "", *, stamped: bool = False) -> None:
        pre = f"rt/{namespace}/" if namespace else "rt/"
        dp = self.dp = DomainParticipant(domain)
        kind = TwistStamped_ if stamped else Twist_
        self.stamped = stamped
        self.cmd = DataWriter(dp, Topic(dp, f"{pre}cmd_vel", kind), qos=RELIABLE)
        self.odom = DataReader(dp, Topic(dp, f"{pre}odom", Odometry_), qos=RELIABLE)
        self.tf = DataReader(dp, Topic(dp, "rt/tf", TFMessage_), qos=RELIABLE)
        self.joints = DataReader(dp, Topic(dp, f"{pre}joint_states", JointState_), qos=RELIABLE)
        self.diagnostics = DataReader(dp, Topic(dp, f"{pre}diagnostics", DiagnosticArray_), qos=RELIABLE)
        self.last_odom = None
        self.last_tf = None
        self.statuses = []

    def send(self, linear_x: float, angular_z: float) -> None:
        twist = Twist_(linear=Vector3_(x=linear_x), angular=Vector3_(z=angular_z))
        self.cmd.write(TwistStamped_(twist=twist) if self.stamped else twist)

    def poll(self) -> None:
        for o in self.odom.take(N=1000):
            if isinstance(o, Odometry_):
                self.last_odom = o
        for tf in self.tf.take(N=1000):
            if isinstance(tf, TFMessage_) and tf.transforms:
                self.last_tf = tf.transforms[-1]
        for d in self.diagnostics.take(N=1000):
            if isinstance(d, DiagnosticArray_):
                self.statuses.extend(d.status)

    def close(self) -> None:
        self.dp = None
