"""``fieldbus scan ethercat IFACE`` / ``fieldbus scan canopen CHANNEL``: what is on a live bus.

EtherCAT (pysoem): per slave position, station address, alias, identity,
SII name, AL state and status code, mailbox protocols, DC, topology,
SyncManagers and the PDO mapping as the slave reports it. CANopen: the nodes
that answer, their identity, device type, name and PDO parameters.
``--write-maps DIR`` writes one drive map per distinct device and a network
file that ``fieldbus run`` brings up as it is.
"""

from __future__ import annotations

import argparse
import json
import shlex
from typing import TYPE_CHECKING, Any

from fieldbus.commands.argtypes import integer, non_negative, positive
from fieldbus.commands.outputs import check_folder
from fieldbus.commands.usage import add_command
from fieldbus.scan.model import Device, as_json

if TYPE_CHECKING:
    from fieldbus.scan.writemaps import Written


def register(sub: Any) -> None:
    p = add_command(
        sub,
        "scan",
        help="list the devices on a live bus (identity, state, PDO mapping); write maps for them",
        doc=__doc__,
        codes=CODES,
    )
    kinds = p.add_subparsers(dest="bus_type", metavar="BUS", required=True)
    e = add_command(
        kinds,
        "ethercat",
        help="scan an EtherCAT segment with pysoem (root or CAP_NET_RAW)",
        doc="Scan an EtherCAT segment with pysoem (root or CAP_NET_RAW): every slave's identity, state, "
        "mailbox,\nDC, topology, SyncManagers and PDO mapping.",
        codes=CODES,
    )
    e.add_argument("interface", metavar="IFACE", help="network card, e.g. eth0")
    e.add_argument("--no-sdo-info", action="store_true", help="do not ask for object names and types")
    e.add_argument(
        "--errors",
        action="store_true",
        help="only the ESC error counters, link state and EEPROM status per slave, and the suspect cable "
        "(read before any configuration, which would clear them; no state changes)",
    )
    e.add_argument(
        "--reset-errors", action="store_true", help="with --errors: clear the counters after reading"
    )
    _common(e, cycle_us=1000, timeout_us=500)
    e.set_defaults(func=run_ethercat)
    c = add_command(
        kinds,
        "canopen",
        help="scan a CAN bus for CANopen nodes (python-can)",
        doc="Scan a CAN bus for CANopen nodes (python-can): the nodes that answer, their identity, device "
        "type,\nname and PDO parameters.",
        codes=CODES,
    )
    c.add_argument("channel", metavar="CHANNEL", help="python-can channel, e.g. can0")
    c.add_argument("--interface", default="socketcan", help="python-can interface (default socketcan)")
    c.add_argument("--bitrate", type=integer(1), help="bit/s (default: the interface's)")
    c.add_argument(
        "--listen", type=non_negative("s"), default=0.3, help="seconds to listen for heartbeats first (0.3)"
    )
    c.add_argument(
        "--probe-timeout", type=positive("s"), default=0.1, help="seconds a probed id may take (0.1)"
    )
    _common(c, cycle_us=5000, timeout_us=2000)
    c.set_defaults(func=run_canopen)


CODES = [
    (0, "the bus was scanned (and, with --write-maps, the maps and network.yaml written)"),
    (
        1,
        "the interface or channel cannot be opened, no EtherCAT slave answers, or the --write-maps folder\ncannot be written",
    ),
]


def _common(p: argparse.ArgumentParser, *, cycle_us: int, timeout_us: int) -> None:
    p.add_argument("--json", action="store_true", help="one JSON object on stdout")
    p.add_argument(
        "--write-maps", metavar="DIR", help="write a drive map per distinct device and network.yaml"
    )
    p.add_argument(
        "--cycle-time-us",
        type=integer(50, 1_000_000),
        default=cycle_us,
        help=f"cycle time in the network file, 50..1000000 ({cycle_us})",
    )
    p.add_argument(
        "--receive-timeout-us",
        type=integer(10, 1_000_000),
        default=timeout_us,
        help=f"receive timeout in the network file, 10..1000000 ({timeout_us})",
    )


def _errors(args: argparse.Namespace) -> int:
    from fieldbus.commands.argtypes import UsageError
    from fieldbus.scan import errors

    if args.write_maps or not args.errors:
        raise UsageError(
            "--errors reads the error counters only: without --write-maps; --reset-errors needs --errors"
        )
    result = errors.read_errors(args.interface, reset=args.reset_errors)
    if args.json:
        print(json.dumps(result.as_json()))
    else:
        print(errors.format_text(result))
    return 0


def _source(args: argparse.Namespace) -> str:
    where = args.interface if args.bus_type == "ethercat" else args.channel
    return f"fieldbus scan {args.bus_type} {shlex.quote(where)}"


def run_ethercat(args: argparse.Namespace) -> int:
    from fieldbus.scan import ethercat

    if args.errors or args.reset_errors:
        return _errors(args)
    from fieldbus.scan.writemaps import BusSpec, Placed, write_maps

    check_folder(args.write_maps, "--write-maps")
    result = ethercat.scan(args.interface, sdo_information=not args.no_sdo_info)
    written = None
    if args.write_maps:
        spec = BusSpec(
            "ethercat",
            args.interface,
            cycle_time_us=args.cycle_time_us,
            receive_timeout_us=args.receive_timeout_us,
        )
        placed = [Placed(s, s.position, coe="CoE" in s.mailbox_protocols) for s in result.slaves]
        written = write_maps(placed, args.write_maps, spec, _source(args))
    if args.json:
        _print_json("ethercat", as_json(result), written)
        return 0
    print(f"{len(result.slaves)} slaves on {args.interface}")
    for s in result.slaves:
        parent = "master" if s.parent is None else str(s.parent)
        print(
            f"{s.position:3d}  0x{s.configured_address:04X}  alias {s.alias:<5d} {s.name}  "
            f"{_ident(s)}  {s.state} (0x{s.al_status_code:04X} {s.al_status})"
        )
        print(
            f"     mailbox {','.join(s.mailbox_protocols) or '-'}  CoE {','.join(s.coe_details) or '-'}  "
            f"DC {'yes' if s.dc else 'no'}  parent {parent}  open ports {','.join(map(str, s.open_ports)) or '-'}"
        )
        sms = ", ".join(f"SM{m.index} {m.type} 0x{m.start:04X}+{m.length}" for m in s.sync_managers)
        print(f"     {sms}")
        _print_pdos(s, f"mapping from {s.mapping_source}")
    _print_written(written)
    return 0


def _print_json(bus: str, scanned: Any, written: Written | None) -> None:
    """The ``--json`` object: the bus kind, what the scan found and, with --write-maps, what was written."""
    out = {"bus": bus, **scanned}
    if written is not None:
        out["written"] = {"network": str(written.network), "maps": [str(p) for p in written.maps]}
    print(json.dumps(out))


def run_canopen(args: argparse.Namespace) -> int:
    from fieldbus.scan import canopen
    from fieldbus.scan.writemaps import BusSpec, Placed, write_maps

    check_folder(args.write_maps, "--write-maps")
    result = canopen.scan(
        args.channel, args.interface, args.bitrate, listen_s=args.listen, probe_timeout_s=args.probe_timeout
    )
    written = None
    if args.write_maps:
        spec = BusSpec(
            "canopen",
            args.channel,
            can_interface=args.interface,
            bitrate=args.bitrate,
            cycle_time_us=args.cycle_time_us,
            receive_timeout_us=args.receive_timeout_us,
        )
        placed = [Placed(n, 0, node_id=n.node_id, heartbeat_ms=n.heartbeat_ms) for n in result.nodes]
        written = write_maps(placed, args.write_maps, spec, _source(args))
    if args.json:
        _print_json("canopen", as_json(result), written)
        return 0
    print(f"{len(result.nodes)} nodes on {args.channel} ({args.interface})")
    for n in result.nodes:
        dt = "-" if n.device_type is None else f"0x{n.device_type:08X}"
        hb = "-" if n.heartbeat_ms is None else f"{n.heartbeat_ms} ms"
        print(
            f"node {n.node_id:3d}  {n.name}  {_ident(n)}  device type {dt}  heartbeat {hb}  "
            f"seen by {n.seen}{'' if n.nmt_state is None else ' (' + n.nmt_state + ')'}"
        )
        _print_pdos(n, "")
    _print_written(written)
    return 0


def _ident(d: Device) -> str:
    i = d.identity
    return f"vendor 0x{i.vendor_id:08X} product 0x{i.product_id:08X} rev 0x{i.revision:08X} serial 0x{i.serial:08X}"


def _print_pdos(d: Device, note: str) -> None:
    for kind, pdos in (("RxPDO", d.rpdo), ("TxPDO", d.tpdo)):
        for p in pdos:
            comm = ""
            if p.cob_id is not None:
                state = "" if p.enabled else " disabled"
                comm = f" COB-ID 0x{p.cob_id:03X}{state} type {p.transmission_type}"
            entries = ", ".join(f"0x{e.index:04X}:{e.sub_index:02X} {e.name} {e.type}" for e in p.entries)
            print(f"     {kind} 0x{p.index:04X}{comm}: {entries or '(empty)'}")
    if note and (d.rpdo or d.tpdo):
        print(f"     ({note})")
    for err in d.errors:
        print(f"     ! {err}")


def _print_written(written: Any) -> None:
    if written is not None:
        print(
            f"wrote {written.network} and {len(written.maps)} drive map(s): {', '.join(p.name for p in written.maps)}"
        )
