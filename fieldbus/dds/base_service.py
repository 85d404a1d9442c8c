"""The served wheeled base: ``cmd_vel`` in, ``odom``, ``tf``, ``joint_states`` and ``diagnostics`` out, in
standard ROS 2 messages, so Nav2 (or any ROS 2 node) drives the base with no node of ours.

:class:`BaseService` runs inside :class:`~fieldbus.dds.server.BusServer`'s cycle. The rules are the served
bus's (docs/dds.md, docs/safety.md):

- **one owner**: the first DDS participant whose ``cmd_vel`` is valid takes the base (it claims the wheel
  groups, as ``cmd_vel:<its GUID>``); another participant's ``cmd_vel`` is refused and counted, whatever
  it says. While a client holds a wheel group by request, ``cmd_vel`` is refused.
- **no transition starts motion**: taking the base enables the wheel drives; until every wheel is
  OPERATION ENABLED the base drops its command and sends zero; commands taken before are not applied.
- **refused, never liveness**: a Twist with NaN or infinity is refused (counted per reason) and does not
  renew the command.
- **timeout**: after ``cmd_vel_timeout`` seconds without a valid command the base ramps to zero within its
  deceleration limits and holds there; when its owner's participant leaves the domain the base ramps
  down the same way and then lets the wheel groups go (IDLE: zero velocity), so a new client can take it.
- **latches**: the bus's safe stop or a drive fault latches the wheel groups as any group; an operator
  claims, clears and releases them with the usual requests; the next ``cmd_vel`` takes the base again.

Jazzy's Nav2 publishes ``geometry_msgs/Twist`` on ``cmd_vel``, Kilted's ``TwistStamped``: both are read.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from cyclonedds.topic import Topic

from fieldbus.core.diffdrive import DiffDriveParams, Limited, quaternion_z
from fieldbus.dds import messages as m
from fieldbus.dds import ros_types as r
from fieldbus.dds.cdr import PlainReader, PlainWriter
from fieldbus.dds.participant import COMMANDS, RELIABLE
from fieldbus.dds.topic_claim import TopicClaim
from fieldbus.errors import FieldbusError
from fieldbus.network import CycleResult, Operational
from fieldbus.wheeled_base import WheeledBase

if TYPE_CHECKING:
    from fieldbus.dds.parts import BusServer, ServedGroup

REASONS = ("not_finite", "not_owner", "wheels_claimed")
OWNER_CHECK_EVERY = 10  # cycles between looks at the owner's liveliness


def base_topics(namespace: str = "") -> dict[str, str]:
    """The base's DDS topics: ROS 2 names with the ``rt/`` prefix, under ``namespace`` if given (``tf`` is
    always the global ``/tf``, as tf2 expects)."""
    pre = f"rt/{namespace.strip('/')}/" if namespace.strip("/") else "rt/"
    return {
        "cmd_vel": f"{pre}cmd_vel",
        "odom": f"{pre}odom",
        "joint_states": f"{pre}joint_states",
        "diagnostics": f"{pre}diagnostics",
        "tf": "rt/tf",
    }


def _covariance(diagonal: tuple[float, ...]) -> list[float]:
    cov = [0.0] * 36
    for i, v in enumerate(diagonal):
        cov[i * 7] = float(v)
    return cov


@dataclass
class BaseCounters:
    """What the base did since serve started (published in its diagnostics)."""

    commands: int = 0  # valid cmd_vel taken
    linear_saturated: int = 0  # cycles a linear limit changed the command
    angular_saturated: int = 0
    timeouts: int = 0  # times the command timed out (ramping to rest)
    owners: int = 0  # times a client took the base


class BaseService:
    """The network file's ``base:`` served over DDS by ``server`` (create it before :meth:`attach`)."""

    def __init__(self, server: BusServer, params: DiffDriveParams, namespace: str = "") -> None:
        self.server = server
        self.params = params
        self.topics = base_topics(namespace)
        self.groups = self._wheel_groups(server, params)
        dp = server.participant.dp
        t = self.topics
        self.twist = PlainReader(dp, Topic(dp, t["cmd_vel"], r.Twist), qos=COMMANDS)
        self.stamped: PlainReader | None = None
        try:  # the same topic name, the other type (Kilted's Nav2): DDS matches writers by type
            self.stamped = PlainReader(dp, Topic(dp, t["cmd_vel"], r.TwistStamped), qos=COMMANDS)
        except Exception as exc:
            raise FieldbusError(f"cannot read TwistStamped on {t['cmd_vel']}: {exc}") from None
        self.odom_writer = PlainWriter(dp, Topic(dp, t["odom"], r.Odometry), qos=RELIABLE)
        self.tf_writer = PlainWriter(dp, Topic(dp, t["tf"], r.TFMessage), qos=RELIABLE)
        self.js_writer = PlainWriter(dp, Topic(dp, t["joint_states"], m.JointState), qos=RELIABLE)
        self.diag_writer = PlainWriter(dp, Topic(dp, t["diagnostics"], m.DiagnosticArray), qos=RELIABLE)
        self.claim = TopicClaim("cmd_vel", server.callers)
        self.base: WheeledBase | None = None
        self.leaving = False  # the owner left: ramping to rest, then the wheels are let go
        self.refusals = dict.fromkeys(REASONS, 0)
        self.last_refusal = ""
        self.counters = BaseCounters()
        self._was_limited = False
        self._was_timed_out = True
        self._events: list[str] = []  # said in the next diagnostics (saturation, timeout, owner)
        self._publish_every = 1
        self._k = 0

    @staticmethod
    def _wheel_groups(server: BusServer, params: DiffDriveParams) -> list[ServedGroup]:
        wheels = set(params.wheel_names)
        groups = []
        for g in server.groups.values():
            mine = [a for a in g.axes if a in wheels]
            if not mine:
                continue
            others = [a for a in g.axes if a not in wheels]
            if others:
                raise FieldbusError(
                    f"base: group '{g.name}' holds wheels ({', '.join(mine)}) and other joints "
                    f"({', '.join(others)}); put the wheel drives on their own bus or map so that the base "
                    "owns whole groups"
                )
            if g.ctrl is None:
                raise FieldbusError(f"base: group '{g.name}' has no CiA 402 drives to enable")
            groups.append(g)
        return groups

    @property
    def owner(self) -> str | None:
        """The DDS participant (GUID) that commands the base, None when nobody does."""
        return self.claim.owner

    def attach(self, op: Operational) -> None:
        self.base = WheeledBase(op, self.params)
        rate = self.params.publish_rate
        self._publish_every = max(1, round(1e6 / (rate * op.cycle_time_us))) if rate > 0 else 1

    # -- before exchange() ------------------------------------------------------------------------
    def take(self, now_s: float) -> None:
        """Take the cmd_vel samples of this cycle (before the groups' gates tick)."""
        base = self.base
        if base is None:
            return
        self._k += 1
        if self.owner is not None and not self.leaving and self._k % OWNER_CHECK_EVERY == 0:
            why = self.claim.lost()
            if why is not None:
                self._leave(why)
        for reader in (self.twist, self.stamped):
            if reader is None:
                continue
            for sample in reader.take(N=32):
                twist = sample.twist if isinstance(sample, r.TwistStamped) else sample
                if not isinstance(twist, r.Twist):
                    continue
                self._offer(reader, sample, twist, now_s)
        if self.claim.enabled:
            self.claim.offer()  # the base commands every cycle (its ramp too): the wheel gates stay COMMANDED

    def _offer(self, reader: Any, sample: Any, twist: r.Twist, now_s: float) -> None:
        lin, ang = twist.linear.x, twist.angular.z
        if not all(math.isfinite(v) for v in (lin, ang, twist.linear.y, twist.angular.x, twist.angular.y)):
            self._refuse("not_finite", "a cmd_vel value is NaN or infinite")
            return
        who = self.claim.who(reader, sample)
        if who is None:
            self._refuse("not_owner", "a cmd_vel from a DDS participant not known yet")
            return
        if self.owner is None:
            busy = self.claim.busy(self.groups)
            if busy is not None:
                self._refuse(
                    "wheels_claimed", f"group '{busy.name}' is claimed by client '{busy.gate.label}'"
                )
                return
            self.claim.take(who, self.groups)
            self.leaving = False
            self.counters.owners += 1
            self._events.append(f"taken by DDS participant {who}")
        if who != self.owner:
            self._refuse("not_owner", f"cmd_vel from DDS participant {who}, not the base's owner")
            return
        self.claim.seen(reader, sample)
        if not self.claim.enabled or self.leaving:
            return  # enabling (commands taken before the drives are enabled do not apply), or letting go
        assert self.base is not None
        self.base.command(lin, ang, now_s)
        self.counters.commands += 1

    def _leave(self, why: str) -> None:
        """The owner is gone (or an operator took a wheel group): ramp to rest, then let the wheels go."""
        self.leaving = True
        self._events.append(f"{why}: ramping to rest")
        assert self.base is not None
        self.base.hold()

    def _refuse(self, reason: str, why: str) -> None:
        self.refusals[reason] += 1
        self.last_refusal = why

    # -- after exchange() -------------------------------------------------------------------------
    def after(self, res: CycleResult, now_s: float, dt_s: float, stamp_ns: int) -> None:
        """Odometry from this cycle's inputs, the wheel targets for the next exchange, and what to publish."""
        base = self.base
        if base is None:
            return
        commanding = self.claim.enabled
        step = base.step(res, now_s, dt_s, enabled=commanding)
        limited = bool(step.linear_limited | step.angular_limited)
        if step.linear_limited:
            self.counters.linear_saturated += 1
        if step.angular_limited:
            self.counters.angular_saturated += 1
        if limited and not self._was_limited:
            self._events.append(self._saturation(step))
        if step.timed_out and not self._was_timed_out and self.owner is not None:
            self.counters.timeouts += 1
            self._events.append(f"cmd_vel timed out ({self.params.cmd_vel_timeout:g} s): ramping to rest")
        self._was_limited, self._was_timed_out = limited, step.timed_out
        if self.leaving and step.linear == 0.0 and step.angular == 0.0:
            self._events.append("at rest: the wheels are let go")
            self.claim.let_go()
            self.leaving = False
        if self._k % self._publish_every == 0:
            self.publish(stamp_ns)
        if self._events:
            self.diag_writer.write(self.diagnostics(stamp_ns))
            self._events = []

    def _saturation(self, step: Any) -> str:
        parts = []
        for what, asked, sent, flags in (
            ("linear.x", step.asked_linear, step.linear, step.linear_limited),
            ("angular.z", step.asked_angular, step.angular, step.angular_limited),
        ):
            if flags:
                names = "+".join((f.name or "").lower() for f in Limited if f and f in flags)
                parts.append(f"{what} {names} limit: asked {asked:g}, sent {sent:g}")
        return "saturated: " + "; ".join(parts)

    def publish(self, stamp_ns: int) -> None:
        """Odometry (pose in the odom frame, twist in the base frame), tf and the wheels' joint states."""
        base = self.base
        assert base is not None
        p, odo = self.params, base.odometry
        header = m.Header(stamp=m.Time.of_ns(stamp_ns), frame_id=p.frame(p.odom_frame_id))
        child = p.frame(p.base_frame_id)
        qx, qy, qz, qw = quaternion_z(odo.heading)
        msg = r.Odometry(header=header, child_frame_id=child)
        msg.pose.pose.position = r.Point(odo.x, odo.y, 0.0)
        msg.pose.pose.orientation = r.Quaternion(qx, qy, qz, qw)
        msg.pose.covariance = _covariance(p.pose_covariance_diagonal)
        msg.twist.twist.linear = r.Vector3(odo.linear, 0.0, 0.0)
        msg.twist.twist.angular = r.Vector3(0.0, 0.0, odo.angular)
        msg.twist.covariance = _covariance(p.twist_covariance_diagonal)
        self.odom_writer.write(msg)
        if p.enable_odom_tf:
            tf = r.TransformStamped(header=header, child_frame_id=child)
            tf.transform.translation = r.Vector3(odo.x, odo.y, 0.0)
            tf.transform.rotation = r.Quaternion(qx, qy, qz, qw)
            self.tf_writer.write(r.TFMessage(transforms=[tf]))
        js = m.JointState(header=m.Header(stamp=m.Time.of_ns(stamp_ns)), name=list(p.wheel_names))
        for w in base.wheels:
            img = w.image.inputs
            js.position.append(float(img[w.position][w.row]) if w.position else math.nan)
            js.velocity.append(float(img[w.velocity][w.row]) if w.velocity else math.nan)
        self.js_writer.write(js)

    def diagnostics(self, stamp_ns: int) -> m.DiagnosticArray:
        """One status, ``fieldbus/base``: WARN while saturating or timed out, with the counters."""
        base = self.base
        last = base.last if base is not None else None
        warn = bool(last and (last.linear_limited or last.angular_limited)) or self._was_timed_out
        c = self.counters
        values = [
            m.KeyValue("owner_participant", self.owner or ""),
            m.KeyValue("commands", str(c.commands)),
            m.KeyValue("linear_saturated_cycles", str(c.linear_saturated)),
            m.KeyValue("angular_saturated_cycles", str(c.angular_saturated)),
            m.KeyValue("timeouts", str(c.timeouts)),
            m.KeyValue("last_refusal", self.last_refusal),
        ]
        values += [m.KeyValue(f"refused/{k}", str(n)) for k, n in self.refusals.items()]
        if last is not None:
            values += [
                m.KeyValue("asked_linear", f"{last.asked_linear:g}"),
                m.KeyValue("sent_linear", f"{last.linear:g}"),
                m.KeyValue("asked_angular", f"{last.asked_angular:g}"),
                m.KeyValue("sent_angular", f"{last.angular:g}"),
            ]
        message = "; ".join(self._events) if self._events else ("idle" if self.owner is None else "OK")
        status = m.DiagnosticStatus(
            level=1 if warn and self.owner is not None else 0,
            name="fieldbus/base",
            message=message,
            hardware_id="base",
            values=values,
        )
        return m.DiagnosticArray(header=m.Header(stamp=m.Time.of_ns(stamp_ns)), status=[status])
