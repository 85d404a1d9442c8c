"""``--can-log FILE`` and ``--pcap FILE``: the flags that log a bus's frames (run, demo).

``--can-log`` goes to every CAN bus (canopen, rawcan) in one of python-can's
formats, chosen by the suffix; ``--pcap`` to every EtherCAT bus on a network
card. With several such buses each gets its own file, the bus name before the
suffix (``log.arm.log``, ``log.legs.log``).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from fieldbus.commands.outputs import check_file
from fieldbus.core.network import NetworkConfig, is_can_type
from fieldbus.errors import FieldbusError


def add_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("bus logs")
    g.add_argument(
        "--can-log",
        metavar="FILE",
        help="every CAN frame sent and received, python-can format by suffix (.log candump, .asc, .blf, .csv, .trc)",
    )
    g.add_argument(
        "--pcap", metavar="FILE", help="every EtherCAT frame of the master's card, both directions"
    )


def bus_options(
    args: argparse.Namespace, net: NetworkConfig, backend: str | None
) -> dict[str, dict[str, object]]:
    """Per-bus backend options for the log flags given; refuses a flag no bus can take."""
    out: dict[str, dict[str, object]] = {}
    wanted = (
        ("can_log", getattr(args, "can_log", None), is_can_type, "a CAN bus"),
        (
            "pcap",
            getattr(args, "pcap", None),
            lambda kind: kind == "ethercat",
            "an EtherCAT bus on a network card",
        ),
    )
    for option, path, takes, what in wanted:
        if not path:
            continue
        buses = [b.name for b in net.buses if takes(backend or b.type)]
        if not buses:
            flag = "--" + option.replace("_", "-")
            raise FieldbusError(f"{flag} needs {what}; this network has none")
        for name in buses:
            out.setdefault(name, {})[option] = str(
                per_bus(Path(path), name) if len(buses) > 1 else Path(path)
            )
    return out


def check_outputs(args: argparse.Namespace) -> None:
    """``--can-log`` and ``--pcap`` can be written (:class:`~fieldbus.commands.outputs.OutputError` if not)."""
    for flag, path in (
        ("--can-log", getattr(args, "can_log", None)),
        ("--pcap", getattr(args, "pcap", None)),
    ):
        check_file(path, flag)


def per_bus(path: Path, bus: str) -> Path:
    """``log.asc`` -> ``log.<bus>.asc``."""
    return path.with_name(f"{path.stem}.{bus}{path.suffix}")
