"""The served bus's ROS 2 services (:mod:`fieldbus.dds.services`) answered from the cycle's thread.

:class:`ServiceHost` holds one request reader and one reply writer per group
and service; :meth:`ServiceHost.poll` (every few cycles) turns each call into
the :class:`~fieldbus.dds.messages.Request` the server already carries out
and answers it with the service's response, its request header echoed.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any

from cyclonedds.topic import Topic

from fieldbus.dds import messages as m
from fieldbus.dds.callers import Caller, Callers
from fieldbus.dds.cdr import PlainReader, PlainWriter
from fieldbus.dds.participant import RELIABLE, Participant
from fieldbus.dds.services import SERVICES, Service, service_topics
from fieldbus.errors import FieldbusError

Outcome = dict[str, Any] | FieldbusError | None
Answer = Callable[[m.Request, Callable[[Outcome], None], Caller], None]


class _Endpoint:
    """One service of one group: its reader of calls and writer of answers."""

    def __init__(self, dp: Any, namespace: str, group: str, service: Service) -> None:
        self.group = group
        self.service = service
        rq, rr = service_topics(namespace, group, service.name)
        self.reader = PlainReader(dp, Topic(dp, rq, service.request), qos=RELIABLE)
        self.writer = PlainWriter(dp, Topic(dp, rr, service.response), qos=RELIABLE)


class ServiceHost:
    """Every group's ROS 2 services; create it before bring-up, :meth:`poll` it from the cycle's thread."""

    def __init__(
        self, participant: Participant, namespace: str, groups: list[str], answer: Answer, callers: Callers
    ) -> None:
        dp = participant.dp
        self._answer = answer
        self._endpoints = [_Endpoint(dp, namespace, g, s) for g in groups for s in SERVICES]
        self._callers = callers
        self.calls = 0

    def poll(self) -> None:
        """Take the calls that came since the last poll and carry each out (answered now or when it ends)."""
        for ep in self._endpoints:
            for call in ep.reader.take(N=8):
                if isinstance(call, ep.service.request):
                    self.calls += 1
                    self._call(ep, call)

    def caller(self, ep: _Endpoint, call: Any) -> Caller:
        """The caller: its DDS participant (one per ROS 2 process); its client id ``ros2-`` and that
        participant's GUID in hex (None and ``ros2-?`` while the writer is not known)."""
        who = self._callers.of(ep.reader, call)
        return Caller.of(self._callers, ep.reader, call, f"ros2-{who or '?'}")

    def _call(self, ep: _Endpoint, call: Any) -> None:
        caller = self.caller(ep, call)
        client = caller.label
        s = ep.service
        verb, argument = s.verb, {}
        if s.name == "claim" and not call.data:
            verb = "release"
        elif s.name == "set_mode":
            text = call.mode.strip()
            argument = {"mode": int(text) if text.isdigit() else text}
        elif s.name in ("sdo_read", "sdo_write"):
            argument = {"axis": call.axis, "index": int(call.index), "sub_index": int(call.sub_index)}
            if s.name == "sdo_write":
                argument["data"] = bytes(call.data).hex()
        req = m.Request(
            client_id=client,
            request_id=int(call.sequence_number) & 0xFFFFFFFF,
            group=ep.group,
            verb=verb,
            argument=json.dumps(argument) if argument else "",
        )

        def respond(outcome: Outcome) -> None:
            reply = s.response(client_guid=call.client_guid, sequence_number=call.sequence_number)
            if isinstance(outcome, FieldbusError):
                reply.success, reply.message = False, f"{type(outcome).__name__}: {outcome}"
            else:
                reply.success = True
                detail = dict(outcome or {})
                if s.name == "sdo_read":
                    reply.data = list(bytes.fromhex(str(detail.pop("data", ""))))
                if verb == "claim":
                    reply.message = f"claimed as client '{client}' (the client_id of its JointCommand)"
                elif detail:
                    reply.message = json.dumps(detail)
            ep.writer.write(reply)

        self._answer(req, respond, caller)
