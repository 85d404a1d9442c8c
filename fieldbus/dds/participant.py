"""Where the DDS traffic goes: the domain, the network interface, the QoS and the topic names.

Domain: ``domain`` if given, else the environment's ``ROS_DOMAIN_ID`` (the
ROS 2 convention; rmw_cyclonedds maps it to the same DDS domain id), else 0.
Interface: ``interface`` if given (a configuration naming that one interface;
``lo`` also turns multicast off and discovers peers by unicast on 127.0.0.1,
since loopback has no multicast), else Cyclone DDS's own choice, which
``CYCLONEDDS_URI`` (an XML text or a file) overrides as usual.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from xml.sax.saxutils import quoteattr

from cyclonedds.core import Policy, Qos
from cyclonedds.domain import Domain, DomainParticipant
from cyclonedds.util import duration

from fieldbus.errors import FieldbusError

MAX_DOMAIN_ID = 232  # the highest id whose default ports fit below 65536 (7400 + 250 * id)

# state and command: a late sample is worth nothing (no retransmission, the newest only)
REALTIME = Qos(
    Policy.Reliability.BestEffort,
    Policy.History.KeepLast(1),
    Policy.Durability.Volatile,
)
# the command reader: best effort as the writers, but a few samples per instance, so that a writer that
# names another client's client_id (the same instance) cannot push the owner's newest command out
COMMANDS = Qos(
    Policy.Reliability.BestEffort,
    Policy.History.KeepLast(8),
    Policy.Durability.Volatile,
)
# requests, replies and diagnostics: few, each one matters
RELIABLE = Qos(
    Policy.Reliability.Reliable(duration(seconds=1)),
    Policy.History.KeepLast(32),
    Policy.Durability.Volatile,
)
# diagnostics: the newest kept for late joiners (a monitor that starts sees it at once); a ROS 2
# subscriber with the default VOLATILE durability still matches
DIAGNOSTICS = Qos(
    Policy.Reliability.Reliable(duration(seconds=1)),
    Policy.History.KeepLast(1),
    Policy.Durability.TransientLocal,
)


def domain_id(domain: int | None) -> int:
    """The DDS domain: ``domain``, else ``$ROS_DOMAIN_ID``, else 0."""
    if domain is None:
        text = os.environ.get("ROS_DOMAIN_ID", "").strip()
        if not text:
            return 0
        try:
            domain = int(text)
        except ValueError:
            raise FieldbusError(f"ROS_DOMAIN_ID must be a whole number, not {text!r}") from None
    if not 0 <= domain <= MAX_DOMAIN_ID:
        raise FieldbusError(f"DDS domain id {domain} out of range 0..{MAX_DOMAIN_ID}")
    return domain


def interface_config(interface: str | None, peers: Sequence[str] = ()) -> str | None:
    """A Cyclone DDS XML configuration for ``interface`` and unicast ``peers``; None: the default one."""
    if interface is None and not peers:
        return None
    general = ""
    if interface is not None:
        general = f"<Interfaces><NetworkInterface name={quoteattr(interface)}/></Interfaces>"
        if interface == "lo":
            general += "<AllowMulticast>false</AllowMulticast>"
            peers = peers or ("127.0.0.1",)
    disco = "".join(f"<Peer address={quoteattr(p)}/>" for p in peers)
    disco = f"<Peers>{disco}</Peers><ParticipantIndex>auto</ParticipantIndex>" if disco else ""
    return f"<General>{general}</General><Discovery>{disco}</Discovery>"


_DOMAINS: dict[int, tuple[str, Domain]] = {}  # configured in this process: Cyclone DDS allows one per id


class Participant:
    """One DDS participant on the chosen domain and interface (keep it on one thread)."""

    def __init__(self, domain: int | None = None, interface: str | None = None, peers: Sequence[str] = ()):
        self.domain_id = domain_id(domain)
        config = interface_config(interface, peers)
        try:
            self._domain = self._configured(config) if config is not None else None
            self.dp = DomainParticipant(self.domain_id)
        except Exception as exc:
            where = f"interface '{interface}'" if interface else "the default interface"
            raise FieldbusError(
                f"cannot join DDS domain {self.domain_id} on {where}: {type(exc).__name__}: {exc}"
            ) from None

    def _configured(self, config: str) -> Domain:
        """The domain with ``config``: configured once per process, shared by its participants."""
        known = _DOMAINS.get(self.domain_id)
        if known is None:
            known = _DOMAINS[self.domain_id] = (config, Domain(self.domain_id, config))
        elif known[0] != config:
            raise FieldbusError(
                f"DDS domain {self.domain_id} is configured differently in this process already"
            )
        return known[1]


def topic_names(namespace: str, group: str) -> dict[str, str]:
    """The DDS topic names of one axis group (ROS 2 names with the ``rt/`` prefix)."""
    base = f"rt/{namespace}/{group}"
    return {
        "joint_states": f"{base}/joint_states",
        "axis_state": f"{base}/axis_state",
        "command": f"{base}/command",
    }


def service_names(namespace: str) -> dict[str, str]:
    """The served bus's request, reply and diagnostics topics."""
    return {
        "request": f"rt/{namespace}/request",
        "reply": f"rt/{namespace}/reply",
        "diagnostics": f"rt/{namespace}/diagnostics",
    }


def check_namespace(namespace: str) -> str:
    """A namespace is ROS-name-like: letters, digits, ``_`` and ``/`` inside."""
    ns = namespace.strip("/")
    if (
        not ns
        or not all(part and (part[0].isalpha() or part[0] == "_") for part in ns.split("/"))
        or not all(c.isalnum() or c in "_/" for c in ns)
    ):
        raise FieldbusError(
            f"namespace {namespace!r}: use letters, digits, '_' and '/' (a ROS 2 name, e.g. 'robot/legs')"
        )
    return ns
