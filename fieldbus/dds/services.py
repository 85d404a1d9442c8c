"""The served bus's requests as ROS 2 services, laid out on DDS the way rmw_cyclonedds lays them out.

A ROS 2 node on rmw_cyclonedds calls them with no bridge. rmw_cyclonedds
(github.com/ros2/rmw_cyclonedds, ``rmw_cyclonedds_cpp/src``) maps service
``/NS/NAME`` to the topics ``rq/NS/NAMERequest`` and ``rr/NS/NAMEReply``
(``namespace_prefix.hpp``: prefixes ``rq``/``rr``; ``rmw_node.cpp``
``make_fqtopic``: prefix + name + ``Request``/``Reply``), names the types
``<pkg>::srv::dds_::<Srv>_Request_`` / ``_Response_``
(``ServiceTypeSupport_impl.hpp``), and puts in front of every request and
reply the request header ``cdds_request_header_t`` {``uint64 guid``: the
client's request writer, ``int64 seq``: its sequence number}
(``serdata.hpp``), which the reply echoes (``rmw_send_response``). On the
wire that is a struct whose first two members are the header, then the
fields of the ``.srv`` part; a ``.srv`` part without fields carries ROS 2's
placeholder ``uint8 structure_needs_at_least_one_member``.

Services, per axis group (``NS`` = the served namespace):

========================  ==========================  =============================================
service                   type                        does
========================  ==========================  =============================================
``/NS/GROUP/claim``       ``std_srvs/srv/SetBool``    true: claim the group, false: release it
``/NS/GROUP/enable``      ``std_srvs/srv/Trigger``    enable the CiA 402 drives (the owner)
``/NS/GROUP/disable``     ``std_srvs/srv/Trigger``    disable them (anyone)
``/NS/GROUP/clear_safe_stop`` ``std_srvs/srv/Trigger``  open the latched safe stop (the owner)
``/NS/GROUP/reset_faults`` ``std_srvs/srv/Trigger``   re-arm every joint's fault-reset budget (the owner)
``/NS/GROUP/home``        ``std_srvs/srv/Trigger``    home with the drives' method (the owner)
``/NS/GROUP/set_mode``    ``fieldbus_msgs/srv/SetMode``  switch the modes of operation (the owner)
``/NS/GROUP/sdo_read``    ``fieldbus_msgs/srv/SdoRead``  read an object of one joint
``/NS/GROUP/sdo_write``   ``fieldbus_msgs/srv/SdoWrite`` write an object of one joint (the owner)
========================  ==========================  =============================================

A caller is known by its DDS participant (one per ROS 2 process): every
service client of one node shares the claim, and the group takes commands from
writers of that participant only. Its client id, for people (``AxisState.owner``),
is ``ros2-`` and the participant's GUID in hex; the claim's reply says it.
"""

# no ``from __future__ import annotations``: cyclonedds resolves the annotations at run time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from cyclonedds.idl import IdlStruct
from cyclonedds.idl import types as t

if TYPE_CHECKING:
    Seq = list
else:
    Seq = t.sequence


@dataclass
class TriggerRequest(IdlStruct, typename="std_srvs::srv::dds_::Trigger_Request_"):
    """std_srvs/Trigger request: no fields (ROS 2's placeholder byte), after the request header."""

    client_guid: t.uint64 = 0
    sequence_number: t.int64 = 0
    structure_needs_at_least_one_member: t.uint8 = 0


@dataclass
class TriggerResponse(IdlStruct, typename="std_srvs::srv::dds_::Trigger_Response_"):
    """std_srvs/Trigger response: success and a message (the error, or what was done)."""

    client_guid: t.uint64 = 0
    sequence_number: t.int64 = 0
    success: bool = False
    message: str = ""


@dataclass
class SetBoolRequest(IdlStruct, typename="std_srvs::srv::dds_::SetBool_Request_"):
    """std_srvs/SetBool request."""

    client_guid: t.uint64 = 0
    sequence_number: t.int64 = 0
    data: bool = False


@dataclass
class SetBoolResponse(IdlStruct, typename="std_srvs::srv::dds_::SetBool_Response_"):
    """std_srvs/SetBool response."""

    client_guid: t.uint64 = 0
    sequence_number: t.int64 = 0
    success: bool = False
    message: str = ""


@dataclass
class SetModeRequest(IdlStruct, typename="fieldbus_msgs::srv::dds_::SetMode_Request_"):
    """fieldbus_msgs/SetMode request: ``string mode`` (a fieldbus.Mode name such as "CSV", or its number)."""

    client_guid: t.uint64 = 0
    sequence_number: t.int64 = 0
    mode: str = ""


@dataclass
class SetModeResponse(IdlStruct, typename="fieldbus_msgs::srv::dds_::SetMode_Response_"):
    """fieldbus_msgs/SetMode response: ``bool success``, ``string message``."""

    client_guid: t.uint64 = 0
    sequence_number: t.int64 = 0
    success: bool = False
    message: str = ""


@dataclass
class SdoReadRequest(IdlStruct, typename="fieldbus_msgs::srv::dds_::SdoRead_Request_"):
    """fieldbus_msgs/SdoRead request: ``string axis`` (a joint name), ``uint16 index``, ``uint8 sub_index``."""

    client_guid: t.uint64 = 0
    sequence_number: t.int64 = 0
    axis: str = ""
    index: t.uint16 = 0
    sub_index: t.uint8 = 0


@dataclass
class SdoReadResponse(IdlStruct, typename="fieldbus_msgs::srv::dds_::SdoRead_Response_"):
    """fieldbus_msgs/SdoRead response: ``bool success``, ``string message``, ``uint8[] data``."""

    client_guid: t.uint64 = 0
    sequence_number: t.int64 = 0
    success: bool = False
    message: str = ""
    data: Seq[t.uint8] = field(default_factory=list)


@dataclass
class SdoWriteRequest(IdlStruct, typename="fieldbus_msgs::srv::dds_::SdoWrite_Request_"):
    """fieldbus_msgs/SdoWrite request: ``string axis``, ``uint16 index``, ``uint8 sub_index``, ``uint8[] data``."""

    client_guid: t.uint64 = 0
    sequence_number: t.int64 = 0
    axis: str = ""
    index: t.uint16 = 0
    sub_index: t.uint8 = 0
    data: Seq[t.uint8] = field(default_factory=list)


@dataclass
class SdoWriteResponse(IdlStruct, typename="fieldbus_msgs::srv::dds_::SdoWrite_Response_"):
    """fieldbus_msgs/SdoWrite response: ``bool success``, ``string message``."""

    client_guid: t.uint64 = 0
    sequence_number: t.int64 = 0
    success: bool = False
    message: str = ""


@dataclass(frozen=True)
class Service:
    """One ROS 2 service of a group: its name, types and the request verb it carries out."""

    name: str
    request: Any
    response: Any
    verb: str


SERVICES = (
    Service("claim", SetBoolRequest, SetBoolResponse, "claim"),  # data false: "release"
    Service("enable", TriggerRequest, TriggerResponse, "enable"),
    Service("disable", TriggerRequest, TriggerResponse, "disable"),
    Service("clear_safe_stop", TriggerRequest, TriggerResponse, "clear_safe_stop"),
    Service("reset_faults", TriggerRequest, TriggerResponse, "reset_faults"),
    Service("home", TriggerRequest, TriggerResponse, "home"),
    Service("set_mode", SetModeRequest, SetModeResponse, "mode"),
    Service("sdo_read", SdoReadRequest, SdoReadResponse, "sdo_read"),
    Service("sdo_write", SdoWriteRequest, SdoWriteResponse, "sdo_write"),
)


def service_topics(namespace: str, group: str, name: str) -> tuple[str, str]:
    """The request and reply topics of service ``/namespace/group/name`` (rmw_cyclonedds' mapping)."""
    base = f"/{namespace}/{group}/{name}"
    return f"rq{base}Request", f"rr{base}Reply"
