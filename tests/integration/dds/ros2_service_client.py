"""A ROS 2-style service client written with cyclonedds and the ROS 2 type layout only: no fieldbus import.

    python ros2_service_client.py NAMESPACE GROUP DOMAIN

Lays the calls out as rmw_cyclonedds does (rmw_cyclonedds_cpp/src: topics
``rq/<service>Request`` / ``rr/<service>Reply``, types
``<pkg>::srv::dds_::<Srv>_Request_`` / ``_Response_``, each sample starting
with the request header: the client's 64-bit id and a 64-bit sequence number,
echoed by the reply). Calls, in order: Trigger ``enable`` before claiming
(refused), SetBool ``claim`` true, Trigger ``enable``, fieldbus_msgs SdoRead of 0x6041
(statusword) until it shows OPERATION ENABLED, SdoRead of 0x6060 (modes of
operation) on the first joint, fieldbus_msgs SetMode to CSV (then SdoRead 0x6061
of the last joint), to "bogus" (refused) and to 8, JointCommands under the client
id the claim's reply names (every joint to its position + 0.2 rad), Trigger
``disable``, SetBool ``claim`` false. Prints
one JSON line: each call's (success, message) and what fieldbus it imported.
"""

import json
import random
import sys
import time
from dataclasses import dataclass, field

from cyclonedds.core import Policy, Qos
from cyclonedds.domain import DomainParticipant
from cyclonedds.idl import IdlStruct
from cyclonedds.idl import types as t
from cyclonedds.idl.annotations import key
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration


# std_srvs/srv/Trigger and SetBool as rmw_cyclonedds puts them on the wire (request header first)
@dataclass
class Trigger_Request_(IdlStruct, typename="std_srvs::srv::dds_::Trigger_Request_"):
    client_guid: t.uint64 = 0
    sequence_number: t.int64 = 0
    structure_needs_at_least_one_member: t.uint8 = 0


@dataclass
class Trigger_Response_(IdlStruct, typename="std_srvs::srv::dds_::Trigger_Response_"):
    client_guid: t.uint64 = 0
    sequence_number: t.int64 = 0
    success: bool = False
    message: str = ""


@dataclass
class SetBool_Request_(IdlStruct, typename="std_srvs::srv::dds_::SetBool_Request_"):
    client_guid: t.uint64 = 0
    sequence_number: t.int64 = 0
    data: bool = False


@dataclass
class SetBool_Response_(IdlStruct, typename="std_srvs::srv::dds_::SetBool_Response_"):
    client_guid: t.uint64 = 0
    sequence_number: t.int64 = 0
    success: bool = False
    message: str = ""


# fieldbus_msgs/srv/SdoRead as docs/dds.md gives it
@dataclass
class SdoRead_Request_(IdlStruct, typename="fieldbus_msgs::srv::dds_::SdoRead_Request_"):
    client_guid: t.uint64 = 0
    sequence_number: t.int64 = 0
    axis: str = ""
    index: t.uint16 = 0
    sub_index: t.uint8 = 0


@dataclass
class SdoRead_Response_(IdlStruct, typename="fieldbus_msgs::srv::dds_::SdoRead_Response_"):
    client_guid: t.uint64 = 0
    sequence_number: t.int64 = 0
    success: bool = False
    message: str = ""
    data: t.sequence[t.uint8] = field(default_factory=list)


@dataclass
class SetMode_Request_(IdlStruct, typename="fieldbus_msgs::srv::dds_::SetMode_Request_"):
    client_guid: t.uint64 = 0
    sequence_number: t.int64 = 0
    mode: str = ""


@dataclass
class SetMode_Response_(IdlStruct, typename="fieldbus_msgs::srv::dds_::SetMode_Response_"):
    client_guid: t.uint64 = 0
    sequence_number: t.int64 = 0
    success: bool = False
    message: str = ""


# the topics' messages (builtin_interfaces/Time, std_msgs/Header, sensor_msgs/JointState; fieldbus_msgs/JointCommand)
@dataclass
class Time_(IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):
    sec: t.int32 = 0
    nanosec: t.uint32 = 0


@dataclass
class Header_(IdlStruct, typename="std_msgs::msg::dds_::Header_"):
    stamp: Time_ = field(default_factory=Time_)
    frame_id: str = ""


@dataclass
class JointState_(IdlStruct, typename="sensor_msgs::msg::dds_::JointState_"):
    header: Header_ = field(default_factory=Header_)
    name: t.sequence[str] = field(default_factory=list)
    position: t.sequence[t.float64] = field(default_factory=list)
    velocity: t.sequence[t.float64] = field(default_factory=list)
    effort: t.sequence[t.float64] = field(default_factory=list)


@dataclass
class JointCommand_(IdlStruct, typename="fieldbus_msgs::msg::dds_::JointCommand_"):
    header: Header_ = field(default_factory=Header_)
    client_id: str = ""
    key("client_id")
    sequence: t.uint64 = 0
    position: t.sequence[t.float64] = field(default_factory=list)
    velocity: t.sequence[t.float64] = field(default_factory=list)
    torque: t.sequence[t.float64] = field(default_factory=list)
    kp: t.sequence[t.float64] = field(default_factory=list)
    kd: t.sequence[t.float64] = field(default_factory=list)


BEST_EFFORT = Qos(Policy.Reliability.BestEffort, Policy.History.KeepLast(1), Policy.Durability.Volatile)
# ROS 2's default service QoS: reliable, keep last 10, volatile
SERVICE_QOS = Qos(Policy.Reliability.Reliable(duration(seconds=1)), Policy.History.KeepLast(10))


class Client:
    """One service client: its own request writer and id, as rclpy creates one per service."""

    def __init__(self, dp: DomainParticipant, service: str, req_type: type, rep_type: type) -> None:
        self.req_type, self.rep_type = req_type, rep_type
        self.writer = DataWriter(dp, Topic(dp, f"rq{service}Request", req_type), qos=SERVICE_QOS)
        self.reader = DataReader(dp, Topic(dp, f"rr{service}Reply", rep_type), qos=SERVICE_QOS)
        self.guid = random.getrandbits(63)
        self.seq = 0

    def call(self, timeout_s: float = 20.0, **fields: object) -> list[object]:
        # like rclpy's wait_for_service: wait until the server's reader and writer are matched
        end = time.monotonic() + timeout_s
        while time.monotonic() < end and not (
            self.writer.get_matched_subscriptions() and self.reader.matched_pub
        ):
            time.sleep(0.01)
        self.seq += 1
        self.writer.write(self.req_type(client_guid=self.guid, sequence_number=self.seq, **fields))
        while time.monotonic() < end:
            for r in self.reader.take(N=16):
                if (
                    isinstance(r, self.rep_type)
                    and r.client_guid == self.guid
                    and r.sequence_number == self.seq
                ):
                    return [r.success, r.message] + ([list(r.data)] if hasattr(r, "data") else [])
            time.sleep(0.005)
        raise SystemExit(f"no reply from {self.writer}")


def newest(states: DataReader, timeout_s: float = 10.0) -> JointState_:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        got = [s for s in states.take(N=16) if isinstance(s, JointState_)]
        if got:
            return got[-1]
        time.sleep(0.002)
    raise SystemExit("no joint states")


def main() -> int:
    ns, group, domain = sys.argv[1], sys.argv[2], int(sys.argv[3])
    dp = DomainParticipant(domain)
    base = f"/{ns}/{group}"
    enable = Client(dp, f"{base}/enable", Trigger_Request_, Trigger_Response_)
    disable = Client(dp, f"{base}/disable", Trigger_Request_, Trigger_Response_)
    claim = Client(dp, f"{base}/claim", SetBool_Request_, SetBool_Response_)
    sdo = Client(dp, f"{base}/sdo_read", SdoRead_Request_, SdoRead_Response_)
    set_mode = Client(dp, f"{base}/set_mode", SetMode_Request_, SetMode_Response_)
    reset_faults = Client(dp, f"{base}/reset_faults", Trigger_Request_, Trigger_Response_)
    calls = {
        "enable_unclaimed": enable.call(),
        "reset_faults_unclaimed": reset_faults.call(),
        "claim": claim.call(data=True),
        "enable": enable.call(),
        "reset_faults": reset_faults.call(),
    }
    # the drives enable over a few cycles: read the first one's statusword (0x6041) until it shows it
    for _ in range(100):
        calls["statusword"] = sdo.call(axis="j0", index=0x6041, sub_index=0)
        if calls["statusword"][0] and calls["statusword"][2][0] & 0x6F == 0x27:  # operation enabled
            break
        time.sleep(0.02)
    calls |= {
        "sdo_read": sdo.call(axis="j0", index=0x6060, sub_index=0),
        "sdo_read_bad": sdo.call(axis="j9", index=0x6098, sub_index=0),
        "set_mode_csv": set_mode.call(mode="CSV"),
        "mode_display_csv": sdo.call(axis="j2", index=0x6061, sub_index=0),
        "set_mode_bad": set_mode.call(mode="bogus"),
        "set_mode_8": set_mode.call(mode="8"),
    }
    # command as the claim's reply says: the client id it names, every joint to its position + 0.2 rad
    states = DataReader(dp, Topic(dp, f"rt/{ns}/{group}/joint_states", JointState_), qos=BEST_EFFORT)
    commands = DataWriter(dp, Topic(dp, f"rt/{ns}/{group}/command", JointCommand_), qos=BEST_EFFORT)
    me = calls["claim"][1].split("'")[1]
    before = newest(states).position
    goal = [p + 0.2 for p in before]
    end, seq = time.monotonic() + 2.0, 0
    while time.monotonic() < end:
        seq += 1
        commands.write(JointCommand_(client_id=me, sequence=seq, position=goal))
        time.sleep(0.002)
    moved = {"before": list(before), "goal": goal, "after": list(newest(states).position)}
    calls |= {"disable": disable.call(), "release": claim.call(data=False)}
    out = {
        "calls": calls,
        "moved": moved,
        "fieldbus_imported": sorted(n for n in sys.modules if n.split(".")[0] == "fieldbus"),
    }
    print(json.dumps(out), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
