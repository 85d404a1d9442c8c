"""Process data of one emulated slave: OD mapping -> layout -> compiled copy to/from ESC memory.

Directions from the master's side: *outputs* = RxPDOs (0x1C12 / 0x16xx, SM2,
the drive receives), *inputs* = TxPDOs (0x1C13 / 0x1Axx, SM3, the drive
transmits). The layout is recomputed from the OD's mapping objects, so SDO
writes to them change what the slave exchanges (applied at PRE-OP -> SAFE-OP).

Byte-aligned maps compile to one ``struct.Struct`` per direction (one
``unpack_from`` / ``pack_into`` per cycle); others fall back to the scalar
reference codec of :mod:`fieldbus.core.pdo.layout`.
"""

from __future__ import annotations

import struct

from fieldbus.core.pdo.layout import DirectionLayout, get_value, layout, set_value
from fieldbus.core.pdo.model import DriveMap
from sim_slaves.od import RXPDO_ASSIGN, TXPDO_ASSIGN, Entry, ObjectDictionary

_FMT = {
    ("int", 8): "b",
    ("int", 16): "h",
    ("int", 32): "i",
    ("int", 64): "q",
    ("uint", 8): "B",
    ("uint", 16): "H",
    ("uint", 32): "I",
    ("uint", 64): "Q",
    ("float", 32): "f",
    ("float", 64): "d",
}


class DirectionCodec:
    """Copies one direction between ESC memory (at ``base``) and OD entries."""

    def __init__(self, lay: DirectionLayout, od: ObjectDictionary) -> None:
        self.layout = lay
        self.size = lay.size
        self.entries: list[Entry] = []
        self._layouts = []
        fmt = "<"
        aligned = True
        for e in lay.entries:
            ch = e.channel
            if ch.is_gap:
                if e.shift or ch.bits % 8:
                    aligned = False
                fmt += "x" * (ch.bits // 8)
                continue
            self.entries.append(od.entry(ch.index, ch.sub_index))
            self._layouts.append(e)
            code = _FMT.get((ch.type.kind, ch.bits))
            if code is None or e.shift:
                aligned = False
                code = "x"
            fmt += code
        self.struct: struct.Struct | None = struct.Struct(fmt) if aligned else None

    def to_od(self, mem: bytearray | memoryview, base: int) -> None:
        """ESC memory -> OD values (outputs: what the master wrote)."""
        if self.struct is not None:
            for entry, value in zip(self.entries, self.struct.unpack_from(mem, base), strict=True):
                entry.value = value
            return
        for entry, el in zip(self.entries, self._layouts, strict=True):
            v = get_value(mem, el, base)
            entry.value = int(v) if isinstance(v, bool) else v

    def from_od(self, mem: bytearray | memoryview, base: int) -> None:
        """OD values -> ESC memory (inputs: what the master will read)."""
        if self.struct is not None:
            try:
                self.struct.pack_into(mem, base, *[e.value for e in self.entries])
                return
            except struct.error:
                pass  # a value out of range or a float in an integer entry: take the masking path
        for entry, el in zip(self.entries, self._layouts, strict=True):
            v = entry.value
            if isinstance(v, bytes):
                continue
            if not el.channel.type.is_float:
                v = int(v)
            set_value(mem, el, v, base)


class ProcessImage:
    """Both directions of one slave, laid out from its OD's current PDO assignment."""

    def __init__(self, od: ObjectDictionary, name: str = "slave") -> None:
        drive = DriveMap(
            name=name,
            vendor_id=0,
            product_id=0,
            rpdo=od.assigned_pdos(RXPDO_ASSIGN) if od.has(RXPDO_ASSIGN) else (),
            tpdo=od.assigned_pdos(TXPDO_ASSIGN) if od.has(TXPDO_ASSIGN) else (),
        )
        lay = layout(drive)
        self.version = od.mapping_version
        self.outputs = DirectionCodec(lay.outputs, od)
        self.inputs = DirectionCodec(lay.inputs, od)
