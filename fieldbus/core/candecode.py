"""CANopen frames decoded per node against a network's drive maps (pure: frames in, text out).

:class:`CanopenDecoder` knows, for each node of a network's CANopen buses, the
COB-ID of every PDO and the layout of its entries. :meth:`CanopenDecoder.decode`
turns one frame (id, data) into a :class:`Decoded` line: PDOs in engineering
units (the map's ``factor``/``offset``), NMT commands, SYNC, EMCY by name,
heartbeats by NMT state, SDO requests and answers (index, sub-index, value,
abort code by name). Segmented SDO uploads are put together and reported
whole when their last segment arrives.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from typing import Any

from fieldbus.core.emcy import emcy_name
from fieldbus.core.network import NetworkConfig
from fieldbus.core.pdo.layout import DirectionLayout, EntryLayout, get_value, layout
from fieldbus.errors import abort_name

COB_NMT, COB_SYNC, COB_TIME = 0x000, 0x080, 0x100
NMT_COMMANDS = {
    1: "start",
    2: "stop",
    0x80: "enter pre-operational",
    0x81: "reset node",
    0x82: "reset communication",
}
NMT_STATES = {0: "boot-up", 4: "stopped", 5: "operational", 0x7F: "pre-operational"}


@dataclass(frozen=True)
class Decoded:
    """One frame's meaning: ``node`` (None: broadcast or unknown), ``kind`` and a text."""

    node: int | None
    kind: str  # rpdo, tpdo, nmt, sync, time, emcy, heartbeat, sdo, unknown
    text: str
    values: dict[str, float | int | bool] = field(default_factory=dict)


@dataclass(frozen=True)
class _Pdo:
    node: int
    slave: str
    kind: str  # rpdo (master -> node) or tpdo (node -> master)
    number: int  # 1-based within its direction
    entries: tuple[EntryLayout, ...]
    byte_offset: int  # of the PDO in the direction image
    size: int  # bytes of the direction image


@dataclass
class _Upload:
    index: int
    sub_index: int
    data: bytearray


class CanopenDecoder:
    """Decode the frames of one network's CANopen buses; unknown ids are reported as such."""

    def __init__(self, net: NetworkConfig) -> None:
        self.pdos: dict[int, _Pdo] = {}
        self.nodes: dict[int, str] = {}  # node id -> slave name
        self._uploads: dict[int, _Upload] = {}
        self._requests: dict[int, tuple[int, int]] = {}  # node -> (index, sub) of the last SDO request
        for bus in net.buses:
            if bus.type != "canopen":
                continue
            for slave in bus.slaves:
                node = slave.node_id
                if node is None:
                    continue
                self.nodes[node] = slave.name
                lay = layout(slave.map, pdo_align=8)
                for kind, pdos, dl in (
                    ("rpdo", slave.map.rpdo, lay.outputs),
                    ("tpdo", slave.map.tpdo, lay.inputs),
                ):
                    for number, (pdo, place) in enumerate(zip(pdos, dl.pdos, strict=True), 1):
                        if pdo.canopen is None:
                            continue
                        entries = tuple(
                            e for e in dl.entries if e.pdo_index == place.index and not e.channel.is_gap
                        )
                        self.pdos[pdo.canopen.cob_id_for(node)] = _Pdo(
                            node, slave.name, kind, number, entries, place.byte_offset, _image_bytes(dl)
                        )

    def decode(self, can_id: int, data: bytes) -> Decoded:
        """The meaning of one frame; never raises on a short or odd payload (it says so)."""
        pdo = self.pdos.get(can_id)
        if pdo is not None:
            return self._pdo(pdo, data)
        if can_id == COB_NMT:
            if len(data) < 2:
                return Decoded(None, "nmt", f"NMT, short frame ({data.hex()})")
            target = "all nodes" if data[1] == 0 else f"node {data[1]}"
            what = NMT_COMMANDS.get(data[0], f"command 0x{data[0]:02X}")
            return Decoded(data[1] or None, "nmt", f"NMT {what} -> {target}")
        if can_id == COB_SYNC:
            return Decoded(None, "sync", "SYNC" + (f" counter {data[0]}" if data else ""))
        if can_id == COB_TIME:
            return Decoded(None, "time", f"TIME {data.hex()}")
        node, base = can_id & 0x7F, can_id & 0x780
        if base == 0x080:
            if len(data) < 3:
                return Decoded(node, "emcy", f"EMCY, short frame ({data.hex()})")
            code, register = struct.unpack_from("<HB", data)
            text = "EMCY error reset" if code == 0 else f"EMCY 0x{code:04X} {emcy_name(code)}"
            return Decoded(node, "emcy", f"{text} (register 0x{register:02X})", {"code": code})
        if base == 0x700:
            state = data[0] & 0x7F if data else -1
            return Decoded(node, "heartbeat", f"heartbeat: {NMT_STATES.get(state, f'state 0x{state:02X}')}")
        if base == 0x600:
            return Decoded(node, "sdo", "SDO request: " + self._sdo_request(node, data))
        if base == 0x580:
            return Decoded(node, "sdo", "SDO answer: " + self._sdo_answer(node, data))
        return Decoded(None, "unknown", f"id 0x{can_id:03X}: {data.hex()}")

    def name(self, node: int | None) -> str:
        """``node 3 (hip)`` for a known node."""
        if node is None:
            return "-"
        slave = self.nodes.get(node)
        return f"node {node}" + (f" ({slave})" if slave else "")

    # -- PDOs ------------------------------------------------------------------
    def _pdo(self, pdo: _Pdo, data: bytes) -> Decoded:
        label = f"{pdo.kind.upper()}{pdo.number}"
        need = max((e.byte_offset + e.span_bytes for e in pdo.entries), default=0) - pdo.byte_offset
        if len(data) < need:
            return Decoded(
                pdo.node, pdo.kind, f"{label}: {len(data)} bytes, the map needs {need} ({data.hex()})"
            )
        image = bytearray(pdo.size)
        image[pdo.byte_offset : pdo.byte_offset + len(data)] = data[: pdo.size - pdo.byte_offset]
        values: dict[str, float | int | bool] = {}
        parts = []
        for e in pdo.entries:
            value = _engineering(e, get_value(image, e), outputs=pdo.kind == "rpdo")
            values[e.name] = value
            unit = f" {e.channel.unit}" if e.channel.unit else ""
            shown = f"{value:.6g}" if isinstance(value, float) else str(value)
            parts.append(f"{e.name}={shown}{unit}")
        return Decoded(pdo.node, pdo.kind, f"{label}: " + ", ".join(parts), values)

    # -- SDO -------------------------------------------------------------------
    def _sdo_request(self, node: int, data: bytes) -> str:
        if len(data) < 8:
            return f"short frame ({data.hex()})"
        ccs = data[0] >> 5
        index, sub = struct.unpack_from("<HB", data, 1)
        obj = f"0x{index:04X}:{sub:02X}"
        if ccs == 1:  # initiate download
            self._requests[node] = (index, sub)
            if data[0] & 0x02:  # expedited
                n = 4 - ((data[0] >> 2) & 3) if data[0] & 0x01 else 4
                return f"write {obj} = {_value(data[4 : 4 + n])}"
            size = struct.unpack_from("<I", data, 4)[0] if data[0] & 0x01 else None
            return f"write {obj}, segmented" + (f" ({size} bytes)" if size is not None else "")
        if ccs == 2:  # initiate upload
            self._requests[node] = (index, sub)
            return f"read {obj}"
        if ccs == 0:
            n = 7 - ((data[0] >> 1) & 7)
            return f"download segment {data[1 : 1 + n].hex()}" + (" (last)" if data[0] & 1 else "")
        if ccs == 3:
            return "upload segment"
        if ccs == 4:
            code = struct.unpack_from("<I", data, 4)[0]
            return f"abort {obj}: 0x{code:08X} {abort_name(code)}"
        return f"command specifier {ccs} ({data.hex()})"

    def _sdo_answer(self, node: int, data: bytes) -> str:
        if len(data) < 8:
            return f"short frame ({data.hex()})"
        scs = data[0] >> 5
        index, sub = struct.unpack_from("<HB", data, 1)
        obj = f"0x{index:04X}:{sub:02X}"
        if scs == 2:  # initiate upload answer
            if data[0] & 0x02:
                n = 4 - ((data[0] >> 2) & 3) if data[0] & 0x01 else 4
                return f"{obj} = {_value(data[4 : 4 + n])}"
            self._uploads[node] = _Upload(index, sub, bytearray())
            size = struct.unpack_from("<I", data, 4)[0] if data[0] & 0x01 else None
            return f"{obj}, segmented" + (f" ({size} bytes)" if size is not None else "")
        if scs == 0:  # upload segment
            n = 7 - ((data[0] >> 1) & 7)
            up = self._uploads.get(node)
            if up is None:
                return f"upload segment {data[1 : 1 + n].hex()} (no transfer started)"
            up.data += data[1 : 1 + n]
            if not data[0] & 1:
                return f"upload segment ({len(up.data)} bytes so far)"
            del self._uploads[node]
            return f"0x{up.index:04X}:{up.sub_index:02X} = {_value(bytes(up.data))} (segmented, last)"
        if scs == 3:
            return f"{obj} written"
        if scs == 1:
            return "download segment acknowledged" + (" (last)" if data[0] & 0x10 else "")
        if scs == 4:
            code = struct.unpack_from("<I", data, 4)[0]
            return f"abort {obj}: 0x{code:08X} {abort_name(code)}"
        return f"command specifier {scs} ({data.hex()})"


def _image_bytes(dl: DirectionLayout) -> int:
    return (dl.bits + 7) // 8


def _engineering(e: EntryLayout, raw: Any, *, outputs: bool) -> float | int | bool:
    """Raw -> the value the process image shows: inputs ``f*raw+o``, outputs ``(raw-o)/f``."""
    ch = e.channel
    if not ch.scaled or isinstance(raw, bool):
        return raw  # type: ignore[no-any-return]
    if outputs:
        return (float(raw) - ch.offset) / ch.factor
    return ch.factor * float(raw) + ch.offset


def _value(b: bytes) -> str:
    """An SDO payload shown as an unsigned little-endian number, or as text when it reads as one."""
    if len(b) > 4 and all(32 <= c < 127 for c in b.rstrip(b"\0")):
        return repr(b.rstrip(b"\0").decode("ascii"))
    if len(b) <= 8:
        v = int.from_bytes(b, "little")
        return f"{v} (0x{v:0{2 * len(b)}X})"
    return b.hex()
