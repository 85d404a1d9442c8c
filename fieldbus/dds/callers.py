"""Who sent a DDS sample: the GUID of its writer's participant, from the sample's info, not from its fields.

Cyclone DDS gives every sample taken from a reader its ``sample_info``;
``publication_handle`` names the writer, and the reader's
``get_matched_publication_data(handle)`` gives that writer's discovery data,
whose ``participant_key`` is the GUID of the participant (one per process, as
a rule) that owns it. A client can put any string into a sample; it cannot make
its samples come from another participant.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

_U64 = (1 << 64) - 1


def _participant_key(reader: Any, handle: int) -> bytes | None:
    """The participant GUID (16 bytes) of the writer ``handle`` matched by ``reader``; None: not known.

    cyclonedds's ``get_matched_publication_data`` builds the whole discovery
    sample in Python, its QoS and XTypes type identifier included: 0.2-0.7 ms,
    in the cycle that takes a new writer's first sample. Its C call takes the
    sample's constructor as an argument: given one that keeps only the
    participant's key and a QoS converter that keeps nothing, it costs 10-20 µs.
    """
    ref = getattr(reader, "_ref", None)
    if _matched_data is not None and isinstance(ref, int):
        key = _matched_data(ref, handle, _keep_participant_key, _no_qos)
        return None if key is None else bytes(key)
    data = reader.get_matched_publication_data(handle)
    return None if data is None else bytes(data.participant_key.bytes)


def _keep_participant_key(_key: bytes, participant_key: bytes, *_rest: Any) -> bytes:
    return participant_key


def _no_qos(_pointer: Any) -> None:
    return None


try:  # the C call behind DataReader.get_matched_publication_data (cyclonedds 0.10-11)
    from cyclonedds._clayer import (  # type: ignore[import-not-found]
        ddspy_get_matched_publication_data as _matched_data,
    )
except ImportError:  # another cyclonedds: its public method, whole
    _matched_data = None


def publication_handle(sample: Any) -> int:
    """The handle of the writer that wrote ``sample`` (0: not known)."""
    return int(getattr(getattr(sample, "sample_info", None), "publication_handle", 0) or 0)


class Callers:
    """Writer handles -> their participant's GUID (hex), looked up once per writer."""

    def __init__(self) -> None:
        self._known: dict[int, str] = {}

    def of(self, reader: Any, sample: Any) -> str | None:
        """The participant GUID (32 hex digits) of the writer of ``sample``; None when it is not known."""
        handle = publication_handle(sample)
        if not handle:
            return None
        who = self._known.get(handle)
        if who is None:
            try:
                key = _participant_key(reader, handle)
            except Exception:  # cyclonedds raises its own DDSException for a writer it no longer knows
                return None
            if key is None:
                return None
            who = self._known[handle] = key.hex()
        return who

    @staticmethod
    def alive(reader: Any, handle: int) -> bool:
        """``reader`` still matches the writer ``handle`` (its participant has not left the domain)."""
        try:  # the matched handles come signed, the sample info's unsigned: compare them as uint64
            return any(h & _U64 == handle & _U64 for h in reader.get_matched_publications())
        except Exception:
            return False


@dataclass(frozen=True)
class Caller:
    """Who made a request: ``who`` its participant's GUID (None: not known), ``label`` the name it gave,
    and the writer it came on (``reader``, ``handle``), whose liveliness stands for the caller's."""

    who: str | None
    label: str
    reader: Any = None
    handle: int = 0

    @classmethod
    def of(cls, callers: Callers, reader: Any, sample: Any, label: str) -> Caller:
        return cls(callers.of(reader, sample), label, reader, publication_handle(sample))
