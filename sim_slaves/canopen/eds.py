"""Describe an emulated node's object dictionary to the ``canopen`` package (what an EDS file would say).

For interop: ``canopen.RemoteNode(node_id, to_canopen_od(node.od))`` lets
canopen's own master read and remap the emulated node's PDOs, and
``canopen.LocalNode(node_id, to_canopen_od(node.od))`` serves the same
objects (access types and current values as defaults) from canopen's own SDO
server.
"""

from __future__ import annotations

from typing import Any

from sim_slaves.od import Access, ObjectDictionary

VISIBLE_STRING = 0x0009  # CiA 301 data type index


def to_canopen_od(ours: ObjectDictionary) -> Any:
    """A ``canopen.ObjectDictionary`` with every object of ``ours`` (records for multi-sub objects)."""
    import canopen
    from canopen.objectdictionary import ODRecord, ODVariable

    od = canopen.ObjectDictionary()  # type: ignore[no-untyped-call]
    for index in ours.indices():
        subs = ours.subindices(index)
        if subs == [0]:
            od.add_object(_variable(ours, index, 0, ODVariable))
            continue
        rec = ODRecord(f"x{index:04X}", index)
        for sub in subs:
            rec.add_member(_variable(ours, index, sub, ODVariable))
        od.add_object(rec)
    return od


def _variable(ours: ObjectDictionary, index: int, sub: int, cls: Any) -> Any:
    e = ours.entry(index, sub)
    var = cls(e.name or f"x{index:04X}_{sub:02X}", index, sub)
    var.data_type = e.dtype.coe_code if e.dtype is not None else VISIBLE_STRING
    var.access_type = _ACCESS[e.access]
    value = e.value
    var.default = value.decode("latin-1") if isinstance(value, bytes) else value
    return var


_ACCESS = {Access.RO: "ro", Access.RW: "rw", Access.CONST: "const"}
