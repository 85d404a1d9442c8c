"""``fieldbus register NETWORK.yaml BUS MOTOR REG [VALUE]``: read or write one register of a raw-CAN motor.

    fieldbus register robot.yaml arm j0 PMAX
    fieldbus register robot.yaml arm j0 TIMEOUT 1000
    fieldbus register robot.yaml arm j0 10 3
    fieldbus register robot.yaml arm j0 PMAX 12.5 --save
    fieldbus register robot.yaml legs a1 0x1234 --type float32
    fieldbus register robot.yaml legs a1 watchdog_timeout 0.2

Damiao motors (family damiao): REG is a register name of the Damiao manual (PMAX, VMAX, TMAX,
CTRL_MODE, TIMEOUT, MST_ID, ESC_ID, KP_ASR..., any case) or its number 0..255; the value is a
float32 or uint32 by the register table (--type for a number outside it). The request goes on
CAN id 0x7FF, the answer comes on the motor's MST_ID (the map's). ODrive controllers (family
odrive, firmware 0.6): REG is an endpoint id (RxSdo / TxSdo; ids depend on the firmware build,
its flat_endpoints.json) or the name of an endpoint in the map's odrive.config; --type float32,
uint32, int32 or bool. A write is confirmed by reading the register back.

The bus is opened alone, outside any cycle: no motor is enabled or commanded, and the command is
refused while a master runs on the CAN channel. Writes go to the motor's RAM (a Damiao motor keeps
them until power-off); --save then stores every register of a Damiao motor to its flash, which the
motor does only while disabled (it does not answer otherwise: exit 1).
"""

from __future__ import annotations

import argparse
import json
import struct
import sys
from typing import Any

from fieldbus.commands.argtypes import UsageError
from fieldbus.commands.usage import FAILED, add_command
from fieldbus.core.canfamily import families
from fieldbus.errors import FieldbusError

EXAMPLES = __doc__.split("\n\n")[1].strip("\n")
CODES = [
    (0, "the register was read, or written and read back with the value written (and saved: --save)"),
    (
        1,
        "the network file, the bus, the motor or the register is unknown or refused, the value does not\n"
        "fit, a master holds the channel, or the motor did not answer (--save: an enabled motor)",
    ),
    (FAILED, "the write was answered but the register reads back another value (printed)"),
]
TYPES = {"float32": "<f", "uint32": "<I", "int32": "<i", "bool": "<I"}


def register(sub: Any) -> None:
    p = add_command(
        sub,
        "register",
        help="read or write one register of a Damiao motor or endpoint of an ODrive on a live bus",
        doc=__doc__,
        codes=CODES,
    )
    p.add_argument("network", metavar="NETWORK.yaml", help="network file naming the bus and its motors")
    p.add_argument("bus", metavar="BUS", help="a rawcan bus of the network")
    p.add_argument("motor", metavar="MOTOR", help="a motor (slave name) on that bus, e.g. j0")
    p.add_argument(
        "reg",
        metavar="REG",
        nargs="?",
        help="register name or number (Damiao), endpoint id or name (ODrive); omit with --clear-fault",
    )
    p.add_argument("value", metavar="VALUE", nargs="?", help="the value to write (omit to read)")
    p.add_argument("--type", dest="type_name", choices=tuple(TYPES), help="value type where REG does not say")
    p.add_argument(
        "--save", action="store_true", help="Damiao: then store the registers to flash (motor disabled)"
    )
    p.add_argument(
        "--clear-fault",
        action="store_true",
        help="clear the motor's fault by its family's clear command (Damiao FF x7 FB, ODrive Clear_Errors, "
        "a declarative map's clear pattern) and show its error code after; the motor stays disabled (in a "
        "running session, backend.recover(motor) clears and enables it)",
    )
    p.add_argument("--json", action="store_true", help="one JSON object on stdout")
    p.set_defaults(func=run)


def parse_value(text: str, type_name: str, where: str) -> float:
    """``text`` as a value of ``type_name`` (float32, uint32, int32, bool); :class:`FieldbusError` if it does not fit."""
    try:
        if type_name == "float32":
            v = float(text)
            struct.pack("<f", v)
            return v
        if type_name == "bool" and text.lower() in ("true", "false"):
            return 1.0 if text.lower() == "true" else 0.0
        n = int(text, 0)
        lo, hi = {"uint32": (0, 0xFFFFFFFF), "int32": (-(1 << 31), (1 << 31) - 1), "bool": (0, 1)}[type_name]
        if not lo <= n <= hi:
            raise ValueError
        return float(n)
    except (ValueError, OverflowError):
        raise FieldbusError(f"{where}: {text!r} is not a {type_name} value") from None


def _as_written(value: float, type_name: str) -> float:
    """``value`` as the register holds it (a float32 register rounds)."""
    return float(struct.unpack("<f", struct.pack("<f", value))[0]) if type_name == "float32" else value


def _show(value: float, type_name: str) -> str:
    return f"{value:g}" if type_name == "float32" else f"{int(value)} (0x{int(value) & 0xFFFFFFFF:X})"


def run(args: argparse.Namespace) -> int:
    bus, slave = _motor(args)
    cfg = slave.map.rawcan
    family = cfg.family if cfg is not None else "none"
    if args.clear_fault:
        if args.reg is not None or args.value is not None or args.save:
            raise UsageError("--clear-fault takes no REG, VALUE or --save")
        return _clear_fault(args, bus, slave)
    if args.reg is None:
        raise UsageError("give REG (a register or endpoint), or --clear-fault")
    registered = families().get(family) if cfg is not None and cfg.protocol is not None else None
    table = registered.register_table if registered is not None else None
    if cfg is None or registered is None:
        raise FieldbusError(
            f"{slave.name} (map {slave.map.name}, family {family}): no registers over CAN; "
            "Damiao (family damiao) and ODrive 0.6 (family odrive) motors have them"
        )
    where = f"{bus.name} {slave.name} (node {slave.node_id})"
    if table is not None:  # a register table (Damiao)
        reg_no, reg_name, type_name, read_only = _table_register(args, table, where)
    else:  # a family on the protocol names its own (ODrive: endpoints; others refuse)
        try:
            reg_no, reg_name, type_name, read_only = registered.register_key(
                cfg.protocol, args.reg, args.type_name, args.value is not None
            )
        except ValueError as exc:
            raise FieldbusError(f"{where} (map {slave.map.name}): {exc}") from None
    value = None if args.value is None else parse_value(args.value, type_name, f"{where} {reg_name}")
    if value is not None and read_only:
        raise FieldbusError(f"{where}: register {reg_name} ({reg_no}) is read-only")
    if args.save and table is None:
        raise FieldbusError(f"{where}: --save stores a Damiao motor's registers; an ODrive saves over USB")
    got = _transfer(bus, slave, table=table is not None, reg=(reg_no, type_name), value=value, save=args.save)
    if value is not None:
        value = _as_written(value, type_name)
    same = value is None or got == value
    label = reg_name if reg_name.endswith(f" {reg_no}") else f"{reg_name} ({reg_no})"
    if args.json:
        out: dict[str, Any] = {
            "bus": bus.name,
            "motor": slave.name,
            "node": slave.node_id,
            "register": reg_no,
        }
        out.update(name=reg_name, type=type_name, value=got, written=value, saved=args.save and same, ok=same)
        print(json.dumps(out))
    elif value is None:
        saved = ", saved to flash" if args.save else ""
        print(f"{where} {label} = {_show(got, type_name)}  [{type_name}]{saved}")
    else:
        back = (
            f", reads back {_show(got, type_name)}" if not same else (", saved to flash" if args.save else "")
        )
        print(f"{where} {label} <- {_show(value, type_name)}  [{type_name}]{back}")
    if not same:
        print(
            f"error: {where}: {label} reads back {_show(got, type_name)} "
            f"after writing {_show(value or 0.0, type_name)}",
            file=sys.stderr,
        )
        return FAILED
    return 0


def _motor(args: argparse.Namespace) -> tuple[Any, Any]:
    """The rawcan bus ``args.bus`` of the network file and its motor ``args.motor``; a clear error naming
    what the file has instead."""
    from fieldbus.core.network import load_network

    net = load_network(args.network)
    bus = next((b for b in net.buses if b.name == args.bus), None)
    if bus is None:
        names = ", ".join(b.name for b in net.buses)
        raise FieldbusError(f"{args.network}: no bus '{args.bus}' (buses: {names})")
    if bus.type != "rawcan":
        raise FieldbusError(f"{args.network}: bus '{bus.name}' is {bus.type}; registers are on rawcan buses")
    slave = next((s for s in bus.slaves if s.name == args.motor), None)
    if slave is None:
        names = ", ".join(s.name for s in bus.slaves)
        raise FieldbusError(f"{args.network}: bus '{bus.name}' has no motor '{args.motor}' (motors: {names})")
    return bus, slave


def _transfer(
    bus: Any, slave: Any, *, table: bool, reg: tuple[int, str], value: float | None, save: bool
) -> float:
    """Write ``value`` (None: only read) to register ``reg`` (number, type) of the motor and read it back:
    with a register ``table``, the family's register (Damiao; ``save``: then stored to flash, when it
    reads back as written), else the family's endpoint access (ODrive: RxSdo). The value read."""
    from fieldbus.backends.rawcan import RawCanBackend

    reg_no, type_name = reg
    backend = RawCanBackend(bus)
    backend.open()
    try:
        i = backend.slave_index(slave.name)
        if table:
            is_float = type_name == "float32"
            if value is not None:
                backend.register(i, reg_no, value, is_float=is_float)
            got = backend.register(i, reg_no, is_float=is_float)
            if save and (value is None or got == _as_written(value, type_name)):
                backend.save_registers(i)
        else:
            fmt = TYPES[type_name]
            data = None if value is None else struct.pack(fmt, value if fmt == "<f" else int(value))
            got = float(struct.unpack(fmt, backend.access(i, reg_no, data))[0])
    finally:
        backend.close()
    return got


def _clear_fault(args: argparse.Namespace, bus: Any, slave: Any) -> int:
    """``--clear-fault``: the family's clear command to one motor; its error code after (Damiao)."""
    from fieldbus.backends.rawcan import RawCanBackend

    where = f"{bus.name} {slave.name} (node {slave.node_id})"
    backend = RawCanBackend(bus)
    backend.open()
    try:
        done = backend.clear_fault(slave.name)
        code = backend.error_code(slave.name)
    finally:
        backend.close()
    if args.json:
        print(
            json.dumps(
                {"bus": bus.name, "motor": slave.name, "node": slave.node_id, "cleared": done, "code": code}
            )
        )
    elif done:
        print(f"{where}: fault cleared (error code now {code:#x}); the motor stays disabled")
    if not done:
        print(
            f"error: {where}: no clear command answered (family {slave.map.rawcan.family})", file=sys.stderr
        )
        return FAILED
    return 0


def _table_register(args: argparse.Namespace, table: Any, where: str) -> tuple[int, str, str, bool]:
    """REG looked up in the family's register table: number, name, type, read-only."""
    found = table.lookup(args.reg)
    if found is None:
        known = ", ".join(r.name for r in table.REGISTERS if not r.read_only)
        raise FieldbusError(f"{where}: no register '{args.reg}': a number 0..255 or a name ({known}...)")
    if not isinstance(found, int):
        type_name = "float32" if found.is_float else "uint32"
        if args.type_name not in (None, type_name):
            raise FieldbusError(f"{where}: register {found.name} ({found.number}) is a {type_name}")
        return found.number, found.name, type_name, found.read_only
    if args.type_name not in (None, "float32", "uint32"):
        raise FieldbusError(f"{where}: Damiao registers are float32 or uint32, not {args.type_name}")
    if args.type_name is None and args.value is not None:
        raise FieldbusError(f"{where}: register {found} is not in the table: give --type float32 or uint32")
    return found, f"register {found}", args.type_name or "uint32", False
