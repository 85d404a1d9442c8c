"""``fieldbus sdo read|write|list BUS TARGET ...``: one SDO on a live bus, or a slave's object dictionary.

    fieldbus sdo read ethercat eth0 --slave 1 0x6060 0 --type int8
    fieldbus sdo write ethercat eth0 --slave 1 0x6060 0 8 --type int8
    fieldbus sdo read canopen can0 --node 3 0x1008 0
    fieldbus sdo list ethercat eth0 --slave 1

EtherCAT slaves are addressed by position (0-based, wire order; SOEM's
``config_init`` puts the segment in PRE-OP first), CANopen nodes by node id.
Values are typed by ``--type`` (int8..uint64, float, double, bool, string,
bytes), else by the slave's SDO Information (EtherCAT), else by the CiA 301 /
CiA 402 object tables. Expedited and segmented transfers; an abort is printed
with its code and name.
"""

from __future__ import annotations

import argparse
import json
from typing import Any

from fieldbus.commands.argtypes import NODE_ID, UsageError, integer, positive
from fieldbus.commands.usage import add_command
from fieldbus.core import datatypes
from fieldbus.core.pdo.names import CIA402_TYPES
from fieldbus.core.sdo import info as sdo_info
from fieldbus.errors import FieldbusError, SdoAbortError

EXAMPLES = __doc__.split("\n\n")[1].strip("\n")
CODES = [
    (0, "the SDO was read or written, or the objects listed"),
    (1, "the bus cannot be opened, no such slave or node, an SDO abort (its code and name),\nor a timeout"),
]
EXTRA_TYPES = ("string", "bytes")
# CiA 301 objects every device has, by (index, sub): what --type defaults to on CANopen
CIA301_TYPES: dict[tuple[int, int], str] = {
    (0x1000, 0): "uint32",
    (0x1001, 0): "uint8",
    (0x1008, 0): "string",
    (0x1009, 0): "string",
    (0x100A, 0): "string",
    (0x1017, 0): "uint16",
    **{(0x1018, s): "uint32" for s in range(1, 5)},
}


def register(sub: Any) -> None:
    p = add_command(
        sub,
        "sdo",
        help="read or write one SDO on a live bus; list a slave's objects (SDO Information)",
        doc=__doc__,
        codes=CODES,
    )
    verbs = p.add_subparsers(dest="verb", metavar="VERB", required=True)
    for verb in ("read", "write", "list"):
        what = "list a slave's objects (SDO Information)" if verb == "list" else f"{verb} one SDO"
        v = add_command(
            verbs, verb, help=what, doc=f"{what[0].upper()}{what[1:]}.\n\n{EXAMPLES}", codes=CODES
        )
        v.add_argument("bus_type", choices=("ethercat", "canopen"), metavar="BUS", help="ethercat | canopen")
        v.add_argument("target", metavar="IFACE|CHANNEL", help="network card (EtherCAT) or CAN channel")
        v.add_argument(
            "--slave", type=integer(0), default=0, help="EtherCAT: slave position, 0-based (default 0)"
        )
        v.add_argument("--node", type=NODE_ID, help="CANopen: node id, 1..127")
        v.add_argument("--interface", default="socketcan", help="CANopen: python-can interface (socketcan)")
        v.add_argument("--bitrate", type=integer(1), help="CANopen: bit/s")
        v.add_argument("--timeout", type=positive("s"), default=0.5, help="CANopen: SDO timeout in s (0.5)")
        v.add_argument("--json", action="store_true", help="one JSON object on stdout")
        if verb != "list":
            v.add_argument(
                "index", type=integer(0, 0xFFFF), metavar="INDEX", help="object index, e.g. 0x6060"
            )
            v.add_argument("sub_index", type=integer(0, 0xFF), metavar="SUB", help="sub-index, e.g. 0")
            if verb == "write":
                v.add_argument(
                    "value", metavar="VALUE", help="the value: a number, text (string) or hex (bytes)"
                )
            v.add_argument(
                "--type", dest="type_name", help="int8..uint64, float, double, bool, string, bytes"
            )
        v.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.bus_type == "canopen" and args.node is None:
        raise UsageError("CANopen: give the node id (--node N)")
    if args.bus_type == "ethercat":
        return _ethercat(args)
    return _canopen(args)


# -- values ------------------------------------------------------------------------------------
def check_type(name: str) -> str:
    if name in EXTRA_TYPES or datatypes.lookup(name) is not None:
        return name
    raise FieldbusError(f"unknown --type {name!r}: use int8..uint64, float, double, bool, string or bytes")


def encode(value: str, type_name: str) -> bytes:
    """``value`` (text from the command line) as SDO bytes of ``type_name``."""
    if type_name == "string":
        return value.encode("latin-1")
    if type_name == "bytes":
        try:
            return bytes.fromhex(value.replace(":", "").replace(" ", ""))
        except ValueError:
            raise FieldbusError(f"bytes are hex, e.g. 01ff20: {value!r}") from None
    dt = datatypes.lookup(type_name)
    assert dt is not None
    try:
        number = float(value) if dt.is_float else int(value, 0)
    except ValueError:
        raise FieldbusError(f"{value!r} is not a {type_name}") from None
    if not dt.fits(number):
        raise FieldbusError(f"{value} does not fit {type_name} ({dt.min:g} .. {dt.max:g})")
    return dt.encode(number)


def decode(raw: bytes, type_name: str | None) -> Any:
    """The value of ``raw`` as ``type_name`` (None: unsigned by length, or hex)."""
    if type_name == "string":
        return raw.split(b"\0", 1)[0].decode("latin-1")
    dt = datatypes.lookup(type_name) if type_name and type_name != "bytes" else None
    if dt is not None and len(raw) == max(1, (dt.bits + 7) // 8):
        return dt.decode(raw)
    if type_name is None and len(raw) in (1, 2, 4, 8):
        return int.from_bytes(raw, "little")
    return raw.hex()


def _print_value(args: argparse.Namespace, raw: bytes, type_name: str | None, where: str) -> None:
    value = decode(raw, type_name)
    if args.json:
        out = {"index": args.index, "sub_index": args.sub_index, "type": type_name, "value": value}
        print(json.dumps({**out, "raw": raw.hex(), "bytes": len(raw)}))
        return
    shown = repr(value) if isinstance(value, str) else str(value)
    if isinstance(value, int) and not isinstance(value, bool):
        shown += f" (0x{value & ((1 << (8 * len(raw))) - 1):0{2 * len(raw)}X})"
    print(
        f"{where} 0x{args.index:04X}:{args.sub_index:02X} = {shown}  [{type_name or 'untyped'}, {len(raw)} bytes]"
    )


# -- EtherCAT ----------------------------------------------------------------------------------
def _ethercat(args: argparse.Namespace) -> int:
    from fieldbus.backends.buslock import lock_network_card

    with lock_network_card(
        args.target
    ):  # refused while a master runs on the card (its slaves would leave OP)
        return _ethercat_locked(args)


def _ethercat_locked(args: argparse.Namespace) -> int:
    from fieldbus.backends.ecat_master import open_segment, sdo
    from fieldbus.scan.ethercat import c_string

    master = open_segment(args.target)
    try:
        if not 0 <= args.slave < len(master.slaves):
            raise FieldbusError(
                f"no slave at position {args.slave}: {len(master.slaves)} slaves on {args.target}"
            )
        s = master.slaves[args.slave]
        where = f"slave {args.slave} ({s.name})"
        if args.verb == "list":
            return _list(args, s, where, c_string)
        type_name = (
            check_type(args.type_name) if args.type_name else _info_type(s, args.index, args.sub_index)
        )
        index, sub = args.index, args.sub_index
        if args.verb == "read":
            raw = bytes(
                sdo(lambda: s.sdo_read(index, sub), index=index, sub_index=sub, slave=where, what="read")
            )
            _print_value(args, raw, type_name, where)
            return 0
        if type_name is None:
            raise FieldbusError(
                f"{where}: the type of 0x{index:04X}:{sub:02X} is unknown (no SDO Information); give --type"
            )
        data = encode(args.value, type_name)
        sdo(lambda: s.sdo_write(index, sub, data), index=index, sub_index=sub, slave=where, what="write")
        _print_written(args, where, type_name, data)
        return 0
    finally:
        master.close()


def _od_entries(slave: Any, index: int | None = None) -> list[tuple[Any, list[Any]]]:
    """(object, its entries) by SDO Information (the EtherCAT adapter's ``object_dictionary``)."""
    from fieldbus.backends.ecat_master import object_dictionary

    return list(object_dictionary(slave, None if index is None else (index,)))


def _info_type(slave: Any, index: int, sub: int) -> str | None:
    """The project type name of ``index:sub`` from SDO Information (None when it cannot tell)."""
    try:
        found = _od_entries(slave, index)
    except FieldbusError:
        return CIA301_TYPES.get((index, sub)) or CIA402_TYPES.get((index, sub))
    for obj, entries in found:
        code = (
            int(obj.data_type)
            if not entries
            else (int(entries[sub].data_type) if sub < len(entries) else None)
        )
        name = sdo_info.TYPE_NAMES.get(code) if code is not None else None
        if name == "string" or (name is not None and datatypes.lookup(name) is not None):
            return name
    return None


def _list(args: argparse.Namespace, slave: Any, where: str, text: Any) -> int:
    objects = []
    for obj, entries in _od_entries(slave):
        item: dict[str, Any] = {
            "index": obj.index,
            "name": text(obj.name),
            "object_code": sdo_info.OBJECT_CODES.get(int(obj.object_code), str(obj.object_code)),
            "type": sdo_info.type_name(int(obj.data_type)),
        }
        subs = entries if entries else []
        if not entries:  # a VAR: its one entry was read with the object (pysoem keeps its access there)
            item["access"] = sdo_info.access_text(int(obj.obj_access))
            item["bits"] = int(obj.bit_length)
        item["entries"] = [
            {
                "sub_index": k,
                "name": text(e.name),
                "type": sdo_info.type_name(int(e.data_type)),
                "bits": int(e.bit_length),
                "access": sdo_info.access_text(int(e.obj_access)),
            }
            for k, e in enumerate(subs)
        ]
        objects.append(item)
    if args.json:
        print(json.dumps({"slave": args.slave, "name": slave.name, "objects": objects}))
        return 0
    print(f"{where}: {len(objects)} objects")
    for o in objects:
        detail = f"{o['type']}, {o.get('bits')} bit, {o.get('access')}" if not o["entries"] else o["type"]
        print(f"0x{o['index']:04X}  {o['object_code']:<6} {o['name']}  [{detail}]")
        for e in o["entries"]:
            print(f"   :{e['sub_index']:02X}  {e['name']}  [{e['type']}, {e['bits']} bit, {e['access']}]")
    return 0


def _print_written(args: argparse.Namespace, where: str, type_name: str, data: bytes) -> None:
    if args.json:
        print(
            json.dumps(
                {"index": args.index, "sub_index": args.sub_index, "type": type_name, "raw": data.hex()}
            )
        )
    else:
        print(
            f"{where} 0x{args.index:04X}:{args.sub_index:02X} <- {args.value} [{type_name}, {len(data)} bytes]"
        )


# -- CANopen -----------------------------------------------------------------------------------
def _canopen(args: argparse.Namespace) -> int:
    from fieldbus.core.sdo.canopen_client import sdo_download, sdo_upload
    from fieldbus.scan.canopen import SdoRunner, open_bus

    if args.verb == "list":
        raise FieldbusError("CANopen has no SDO Information service: the device's EDS file lists its objects")
    where = f"node {args.node}"
    known = CIA301_TYPES.get((args.index, args.sub_index)) or CIA402_TYPES.get((args.index, args.sub_index))
    type_name = check_type(args.type_name) if args.type_name else known
    if args.verb == "write":
        if type_name is None:
            raise FieldbusError(f"{where}: give --type for 0x{args.index:04X}:{args.sub_index:02X}")
        data = encode(args.value, type_name)
        steps = sdo_download(args.index, args.sub_index, data)
    else:
        steps = sdo_upload(args.index, args.sub_index)
    bus = open_bus(args.target, args.interface, args.bitrate)
    try:
        result = SdoRunner(bus, args.timeout).run({args.node: steps})[args.node]
    finally:
        bus.shutdown()
    if isinstance(result, SdoAbortError):
        raise SdoAbortError(
            result.code, index=result.index, sub_index=result.sub_index, slave=where
        ) from None
    if isinstance(result, FieldbusError):
        raise result
    if args.verb == "write":
        _print_written(args, where, type_name or "bytes", data)
    else:
        _print_value(args, bytes(result), type_name, where)
    return 0
