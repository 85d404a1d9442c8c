"""The CoE SDO Information server of one emulated slave (ETG.1000.6 §5.6.3), from its object dictionary.

Answers Get OD List, Get Object Description and Get Entry Description;
unknown objects and sub-indices get an SDO Information error with the CiA 301
abort code. Answers longer than the slave's send mailbox go out in
fragments (several mailbox messages), as :func:`fieldbus.core.sdo.info.fragments` cuts them.
"""

from __future__ import annotations

import struct

from fieldbus.core.sdo import info
from fieldbus.core.sdo.info import InfoOpcode, ListType
from fieldbus.errors import SdoAbortError
from sim_slaves.od import (
    PDO_RX,
    PDO_TX,
    RXPDO_ASSIGN,
    RXPDO_MAP,
    TXPDO_ASSIGN,
    TXPDO_MAP,
    Access,
    Entry,
    ObjectDictionary,
    entry_type_code,
)

ABORT_COMMAND = 0x05040001
ABORT_NO_OBJECT = 0x06020000
ABORT_NO_SUBINDEX = 0x06090011


def entry_access(index: int, e: Entry) -> int:
    """ETG.1000.6 object access bits of one entry: read/write per state, PDO mapping."""
    bits = info.ACCESS_READ
    if e.access is Access.RW:
        pdo_config = index in RXPDO_MAP or index in TXPDO_MAP or index in (RXPDO_ASSIGN, TXPDO_ASSIGN)
        bits |= info.ACCESS_WRITE_PREOP if pdo_config else info.ACCESS_WRITE
    if e.mappable:
        bits |= (info.ACCESS_RXPDO if e.pdo_dir & PDO_RX else 0) | (
            info.ACCESS_TXPDO if e.pdo_dir & PDO_TX else 0
        )
    return bits


def handle(od: ObjectDictionary, coe: bytes, room: int) -> list[bytes]:
    """The answer payloads (one or more fragments of at most ``room`` bytes) to one request."""
    if len(coe) < info.HEADER.size:
        return [info.error_payload(ABORT_COMMAND)]
    opcode = coe[2] & 0x7F
    body = coe[info.HEADER.size :]
    try:
        if opcode == InfoOpcode.OD_LIST_REQ and len(body) >= 2:
            (list_type,) = struct.unpack_from("<H", body)
            data = struct.pack("<H", list_type) + _od_list(od, list_type)
            return info.fragments(InfoOpcode.OD_LIST_RES, data, room)
        if opcode == InfoOpcode.OD_REQ and len(body) >= 2:
            (index,) = struct.unpack_from("<H", body)
            return info.fragments(InfoOpcode.OD_RES, _object(od, index), room)
        if opcode == InfoOpcode.OE_REQ and len(body) >= 4:
            index, sub, vinfo = struct.unpack_from("<HBB", body)
            return info.fragments(InfoOpcode.OE_RES, _entry(od, index, sub, vinfo), room)
    except SdoAbortError as e:
        return [info.error_payload(e.code)]
    return [info.error_payload(ABORT_COMMAND)]


def _od_list(od: ObjectDictionary, list_type: int) -> bytes:
    lists = {
        ListType.ALL: od.indices(),
        ListType.RXPDO: [i for i in od.indices() if _maps(od, i, PDO_RX)],
        ListType.TXPDO: [i for i in od.indices() if _maps(od, i, PDO_TX)],
        ListType.BACKUP: [],
        ListType.SETTINGS: [],
    }
    if list_type == ListType.COUNTS:
        return struct.pack("<5H", *(len(lists[t]) for t in sorted(lists)))
    if list_type not in lists:
        raise SdoAbortError(ABORT_COMMAND, index=0, sub_index=0, detail=f"OD list type {list_type}")
    indices = lists[ListType(list_type)]
    return struct.pack(f"<{len(indices)}H", *indices)


def _maps(od: ObjectDictionary, index: int, direction: int) -> bool:
    return any(
        od.entry(index, s).mappable and od.entry(index, s).pdo_dir & direction for s in od.subindices(index)
    )


def _object(od: ObjectDictionary, index: int) -> bytes:
    subs = od.subindices(index)
    if not subs:
        raise SdoAbortError(ABORT_NO_OBJECT, index=index, sub_index=0)
    name = od.object_name(index).encode("latin-1", "replace")
    return struct.pack("<HHBB", index, od.object_data_type(index), max(subs), od.object_code(index)) + name


def _entry(od: ObjectDictionary, index: int, sub: int, value_info: int) -> bytes:
    e = od.entry(index, sub)  # aborts 0x06020000 / 0x06090011
    bits = 8 * e.size if e.dtype is None else e.dtype.bits
    name = (e.name or f"SubIndex {sub:03d}").encode("latin-1", "replace")
    head = struct.pack(
        "<HBBHHH", index, sub, value_info & 0x07, entry_type_code(e), bits, entry_access(index, e)
    )
    return head + name
