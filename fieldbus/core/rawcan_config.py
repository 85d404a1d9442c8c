"""A raw-CAN drive map's ``rawcan:`` section as data: frame fields, CAN ids, special frames (the parser: rawcan).

:class:`~fieldbus.core.pdo.model.DriveMap` holds one; it names the family
protocols' data classes only as types, so the map model sits below the
families' parsers and codecs.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from fieldbus.core.cubemars import CubemarsProtocol
    from fieldbus.core.damiao import DamiaoProtocol
    from fieldbus.core.framespec import FramesProtocol
    from fieldbus.core.odrive import OdriveProtocol

MIT_ENTER = bytes([0xFF] * 7 + [0xFC])
MIT_EXIT = bytes([0xFF] * 7 + [0xFD])
MIT_ZERO = bytes([0xFF] * 7 + [0xFE])


@dataclass(frozen=True)
class RawCanField:
    """One field of a frame, in frame order (first = most significant bits)."""

    name: str
    bits: int
    min: float | None = None
    max: float | None = None
    unit: str | None = None
    safe_value: float | None = None  # command fields: what the safe stop sends (engineering units)
    type: str = "uint"  # uint | int | float32 (byte_order little)

    @property
    def scaled(self) -> bool:
        return self.min is not None


@dataclass(frozen=True)
class RawCanConfig:
    """Frame ids and special frames. CAN ids: command ``command_id + node_id``;
    replies ``reply_id`` (one id for every motor), or ``node_id + reply_id_offset``
    (Damiao's MST_ID), or else the command's id; routed by the ``node_field`` reply
    field (the motor id byte) when there is one, else by their CAN id."""

    command: tuple[RawCanField, ...]
    reply: tuple[RawCanField, ...]
    command_id: int = 0
    reply_id: int | None = None
    node_field: str | None = None
    span: str = "full"  # "full": 2**bits - 1 steps; "power_of_two": 2**bits
    enter: bytes = MIT_ENTER
    exit: bytes = MIT_EXIT
    zero: bytes = MIT_ZERO
    family: str = "mit"
    reply_id_offset: int | None = None
    # a built-in family's own section (CanFamily.section) also under its name; other families' in sections
    damiao: DamiaoProtocol | None = field(
        default=None, metadata={"section": True}
    )  # modes, registers, errors
    odrive: OdriveProtocol | None = field(default=None, metadata={"section": True})  # CANSimple
    byte_order: str = "big"  # "little": fields LSB first in frame order (the image row is the frame)
    cubemars: CubemarsProtocol | None = field(default=None, metadata={"section": True})  # servo or MIT
    frames: FramesProtocol | None = None  # family "frames": the protocol described in data
    protocol: Any = None  # a family on the protocol (fieldbus.core.canfamily): its parsed map section
    #: (key, config) of the family's own part of a classic section (CanFamily.parse_section)
    sections: tuple[tuple[str, Any], ...] = ()

    def section(self, key: str) -> Any:
        """The parsed part ``rawcan.<key>`` of a classic section, None when the map has none (a built-in
        family's: its field of that name, which ``dataclasses.replace`` may have changed)."""
        if key in SECTION_FIELDS:
            return getattr(self, key)
        return dict(self.sections).get(key)

    def reply_can_id(self, node: int) -> int:
        """The CAN id motor ``node`` answers on."""
        if self.reply_id is not None:
            return self.reply_id
        if self.reply_id_offset is not None:
            return node + self.reply_id_offset
        return self.command_id + node


#: The fields holding a built-in family's own section under its key (filled by the parser from ``sections``)
SECTION_FIELDS = frozenset(f.name for f in fields(RawCanConfig) if f.metadata.get("section"))
