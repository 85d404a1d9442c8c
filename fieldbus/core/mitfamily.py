"""The MIT-mode family (``rawcan: family: mit``) on the family protocol (:mod:`fieldbus.core.canfamily`).

One command frame per motor on ``command_id + node_id`` (the image's output row, its bytes reversed for
the MIT layout's big-endian fields, as is with ``byte_order: little``); one reply per motor on its reply
id, routed by the reply's node byte (``node_field``) or by the id alone, copied into the input row the
same way. Enter / exit / zero motor mode are the map's special frames, each answered by a reply. MIT
motors report no error code and have no clear command. The map section is the classic ``rawcan:`` one
(:func:`fieldbus.core.rawcan.parse_classic`).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from fieldbus.core.canfamily import CanFamily, FamilyMotor, Frame, FrameTime, Request
from fieldbus.core.rawcan import RawCanConfig, RawCanField, encode_frame
from fieldbus.core.yamlsrc import PathT

SPECIAL = {"enable": "enter", "disable": "exit", "zero": "zero"}  # the protocol's names -> the map's


@dataclass
class MitFrame:
    """A motor's command frame: ``data`` rewritten from ``source`` (its output row in frame order)."""

    can_id: int
    extended: bool
    data: bytearray
    source: Any
    target: Any


class MitFamily(CanFamily):
    """The MIT motors of one bus; a motor's ``config`` is its :class:`~fieldbus.core.rawcan.RawCanConfig`."""

    name = "mit"
    emulator = "sim_slaves.mit_motor:MitMotorSimulator"

    def __init__(self, motors: Sequence[FamilyMotor]) -> None:
        super().__init__(motors)
        self._frames: list[MitFrame] = []
        self._route: dict[tuple[int, int], int] = {}  # (reply id, node byte or -1) -> motor index
        self._node_byte: dict[int, int] = {}  # reply id -> the node byte's index, or -1
        self._replies: dict[int, Any] = {}  # motor index -> its input row in frame order
        for m in motors:
            cfg, little = m.config, m.config.byte_order == "little"
            data = bytearray(m.outputs.size)
            src = m.outputs if little else m.outputs[::-1]
            self._frames.append(
                MitFrame(cfg.command_id + m.node, False, data, src, np.frombuffer(data, dtype=np.uint8))
            )
            self._replies[m.index] = m.inputs if little else m.inputs[::-1]
            byte = _node_byte(cfg)
            reply_id = cfg.reply_can_id(m.node)
            self._node_byte[reply_id] = byte
            key = (reply_id, m.node if byte >= 0 else -1)
            if key in self._route:
                raise ValueError(f"two motors answer as CAN id 0x{reply_id:X} node {m.node}")
            self._route[key] = m.index

    @classmethod
    def parse(cls, r: Any, raw: Any, path: PathT) -> tuple[Any, tuple[Any, ...], tuple[Any, ...]]:
        from fieldbus.core.rawcan import parse_classic

        return parse_classic(r, raw)

    @classmethod
    def wire_frames(cls, name: str, config: Any, node: int) -> list[FrameTime]:
        command = FrameTime(
            config.command_id + node, sum(f.bits for f in config.command) // 8, f"{name} command"
        )
        reply_bytes = sum(f.bits for f in config.reply) // 8
        return [
            command,
            FrameTime(config.reply_can_id(node), reply_bytes, f"{name} reply", after=command.label),
        ]

    def cycle(self) -> list[MitFrame]:
        for f in self._frames:
            np.copyto(f.target, f.source)
        return self._frames

    def carries(self, can_id: int, extended: bool, data: bytes) -> list[int]:
        byte = self._node_byte.get(can_id)
        if extended or byte is None:
            return []
        node = (data[byte] if byte < len(data) else -2) if byte >= 0 else -1
        i = self._route.get((can_id, node))
        if i is None or len(data) != self._replies[i].size:
            return []
        return [i]

    def route(self, can_id: int, extended: bool, data: bytes) -> list[int]:
        motors = self.carries(can_id, extended, data)
        for i in motors:
            self._replies[i][:] = np.frombuffer(data, dtype=np.uint8)
        return motors

    def commands(self, which: str, motor: int | None = None) -> list[Frame]:
        kind = SPECIAL.get(which)
        if kind is None:
            return []
        return [
            (m.config.command_id + m.node, False, bytes(getattr(m.config, kind)))
            for m in self.motors.values()
            if motor is None or m.index == motor
        ]

    def stop_frames(self) -> list[Frame]:
        """None: the safe stop is the image's safe values, sent by the cycles before exit."""
        return []

    def error(self, motor: int) -> tuple[int, str | None] | None:
        return None

    def bring_up(self, which: str) -> Iterator[Request]:
        """Enter / exit / zero: the map's frame to each motor, its reply awaited; nothing to clear."""
        kind = {"enter": "enable", "exit": "disable"}.get(which, which)
        for m in self.motors.values():
            yield from (Request(f, (m.index,)) for f in self.commands(kind, m.index))

    def recover(self, motor: int) -> Iterator[Request]:
        """Enter motor mode again, answered (an MIT motor has no clear command)."""
        yield from (Request(f, (motor,)) for f in self.commands("enable", motor))


def _node_byte(cfg: Any) -> int:
    """The reply's node byte index, or -1 (routed by its id alone); ValueError when not a whole byte."""
    if not cfg.node_field:
        return -1
    bit = 0
    for f in cfg.reply:
        if f.name == cfg.node_field:
            if bit % 8 or f.bits != 8:
                raise ValueError("node_field must be a whole byte of the reply")
            return bit // 8
        bit += f.bits
    return -1


def field_place(cfg: RawCanConfig, name: str) -> tuple[int, int, int]:
    """``(byte, shift, mask)`` of reply field ``name`` in the frame; ValueError when it spans two bytes."""
    bit = 0
    for f in cfg.reply:
        if f.name == name:
            if bit // 8 != (bit + f.bits - 1) // 8:
                raise ValueError("the error field must sit inside one byte")
            return bit // 8, 8 - (bit % 8) - f.bits, (1 << f.bits) - 1
        bit += f.bits
    raise ValueError(f"no reply field '{name}'")


def safe_patch(cfg: RawCanConfig) -> Callable[[bytearray], None]:
    """Puts the safe values' raw bits into an MIT frame (big-endian, fields MSB first)."""
    total = sum(f.bits for f in cfg.command)
    keep, put, bit = (1 << total) - 1, 0, total
    for f in cfg.command:
        bit -= f.bits
        if f.safe_value is not None:
            pad = RawCanField("pad", -f.bits % 8)  # encode_frame packs whole bytes
            fields = (f, pad) if pad.bits else (f,)
            raw = int.from_bytes(encode_frame(fields, cfg.span, {f.name: f.safe_value}), "big") >> pad.bits
            keep &= ~(((1 << f.bits) - 1) << bit)
            put |= raw << bit
    n = total // 8

    def safe(data: bytearray) -> None:
        x = int.from_bytes(data[:n], "big") & keep | put
        data[:n] = x.to_bytes(n, "big")

    return safe
