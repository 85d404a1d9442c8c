"""``fieldbus decode LOG --network NET``: a CAN log decoded per node.

LOG is any format python-can reads (candump ``.log``, ``.asc``, ``.blf``,
``.csv``, ``.trc``), e.g. one written with ``--can-log``. Each frame becomes one
line: time, direction, node, meaning (PDOs in engineering units from the
network's drive maps, NMT, SYNC, EMCY by name, heartbeats, SDO transfers with
abort codes by name). ``--node N`` keeps one node's frames. Exit 1 with the
line number when the log is malformed.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from fieldbus.commands.argtypes import NODE_ID
from fieldbus.commands.usage import add_command
from fieldbus.core.candecode import CanopenDecoder
from fieldbus.core.network import load_network
from fieldbus.errors import FieldbusError


def register(sub: Any) -> None:
    p = add_command(
        sub,
        "decode",
        help="decode a CAN log per node against a network",
        doc=__doc__,
        codes=[
            (0, "every frame of the log was read and printed"),
            (1, "the log is malformed (its line is named), missing, or the network file is invalid"),
        ],
    )
    p.add_argument("log", metavar="LOG", help="CAN log (.log candump, .asc, .blf, .csv, .trc)")
    p.add_argument("--network", required=True, metavar="NET.yaml", help="the network the log was taken on")
    p.add_argument("--node", type=NODE_ID, help="only this node's frames, 1..127 (and broadcasts to all)")
    p.add_argument("--json", action="store_true", help="one JSON object on stdout")
    p.set_defaults(func=run)


def read_log(path: Path) -> list[Any]:
    """Every frame of a python-can log; a malformed one raises FieldbusError naming its line."""
    try:
        import can
    except ImportError as exc:
        raise FieldbusError("decode needs python-can: pip install 'fieldbus[can]'") from exc
    if not path.is_file():
        raise FieldbusError(f"{path}: no such log file")
    frames: list[Any] = []
    try:
        for msg in can.LogReader(str(path)):
            frames.append(msg)
    except Exception as exc:  # python-can's readers raise ValueError, IndexError, struct.error ...
        raise FieldbusError(f"{path}:{_bad_line(path, len(frames))}: malformed log entry ({exc})") from exc
    return frames


def _bad_line(path: Path, good: int) -> str:
    """Line of the frame after ``good`` readable ones (text formats with one frame per line)."""
    if path.suffix.lower() != ".log":
        return f"frame {good + 1}"
    seen = 0
    for number, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
        if line.strip():
            seen += 1
            if seen == good + 1:
                return str(number)
    return "end"


def run(args: argparse.Namespace) -> int:
    net = load_network(args.network)
    decoder = CanopenDecoder(net)
    frames = read_log(Path(args.log))
    t0 = frames[0].timestamp if frames else 0.0
    rows = []
    for msg in frames:
        d = decoder.decode(msg.arbitration_id, bytes(msg.data))
        if args.node is not None and d.node not in (args.node, None):
            continue
        rows.append(
            {
                "t_s": round(msg.timestamp - t0, 6),
                "direction": "rx" if msg.is_rx else "tx",
                "id": msg.arbitration_id,
                "node": d.node,
                "kind": d.kind,
                "text": d.text,
                "values": d.values,
            }
        )
    if args.json:
        print(json.dumps({"log": str(args.log), "frames": len(frames), "decoded": rows}))
        return 0
    for r in rows:
        print(
            f"{r['t_s']:12.6f}  {r['direction']}  0x{r['id']:03X}  {decoder.name(r['node']):<18} {r['text']}"
        )
    return 0
