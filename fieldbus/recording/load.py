"""Read a recording back: per-bus and per-group numpy structured arrays plus the events.

    rec = fieldbus.recording.load("run.mcap")
    q = rec.groups["joints"]["inputs"]["position_actual_value"]   # (cycles, axes), rad
    pandas.DataFrame(q, index=rec.cycles["cycle"], columns=rec.axes["joints"])

A file cut short (a crash, a full disk) loads up to its last complete block;
:attr:`Recording.complete` says whether the file was finished.
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from fieldbus.errors import BackendUnavailableError, FieldbusError
from fieldbus.recording import schema


@dataclass
class Recording:
    """One recording. Arrays have one row per recorded cycle, in cycle order (``cycle`` field)."""

    path: Path
    meta: dict[str, str]  # the "fieldbus" metadata record (network, cycle_time_us, raw, ...)
    cycles: npt.NDArray[Any]  # schema.cycle_dtype()
    buses: dict[str, npt.NDArray[Any]]  # schema.bus_dtype(...)
    groups: dict[str, npt.NDArray[Any]]  # schema.group_dtype(...): fields outputs, inputs (cycles, axes)
    events: list[dict[str, Any]]  # schema.EVENT_SCHEMA, by cycle
    slaves: dict[str, list[str]] = field(default_factory=dict)  # bus -> slave names (the fresh columns)
    axes: dict[str, list[str]] = field(default_factory=dict)  # group -> axis (slave) names
    units: dict[str, dict[str, dict[str, str]]] = field(
        default_factory=dict
    )  # group -> direction -> channel -> unit
    stats: dict[str, str] = field(default_factory=dict)  # "fieldbus.stats" (written on close)
    complete: bool = True  # False: the file ends early (loaded up to its last complete block)

    @property
    def dropped_blocks(self) -> int:
        return int(self.stats.get("dropped_blocks", 0))


def load(path: str | Path) -> Recording:
    """Load the MCAP recording at ``path``; :class:`FieldbusError` naming the file when it is not one."""
    try:
        from mcap.exceptions import McapError
        from mcap.records import Channel, Footer, Message, Metadata
        from mcap.stream_reader import StreamReader
    except ImportError:
        raise BackendUnavailableError(
            "reading recordings needs mcap: pip install 'fieldbus[record]'"
        ) from None
    p = Path(path)
    channels: dict[int, Channel] = {}
    parts: dict[int, list[bytes]] = {}
    events: list[dict[str, Any]] = []
    meta: dict[str, str] = {}
    stats: dict[str, str] = {}
    complete = False
    try:
        with open(p, "rb") as f:
            try:
                for record in StreamReader(f, record_size_limit=1 << 31).records:
                    if isinstance(record, Channel):
                        channels[record.id] = record
                        if "dtype" in record.metadata:
                            parts.setdefault(record.id, [])
                    elif isinstance(record, Message):
                        ch = channels.get(record.channel_id)
                        if ch is None:
                            continue
                        if ch.topic == "/events":
                            events.append(json.loads(record.data))
                        else:
                            parts[record.channel_id].append(record.data)
                    elif isinstance(record, Metadata):
                        if record.name == "fieldbus":
                            meta = dict(record.metadata)
                        elif record.name == "fieldbus.stats":
                            stats = dict(record.metadata)
                    elif isinstance(record, Footer):
                        complete = True
            # cut short: keep what came whole (mcap raises struct.error for a record cut inside its header)
            except (McapError, EOFError, ValueError, struct.error) as exc:
                if not meta:
                    raise FieldbusError(
                        f"{p}: not a fieldbus recording ({type(exc).__name__})"  # its text quotes bytes
                    ) from None
    except OSError as exc:
        raise FieldbusError(f"cannot read recording {p}: {exc.strerror or exc}") from None
    if meta.get("format") != schema.FORMAT:
        raise FieldbusError(
            f"{p}: not a fieldbus recording (format {meta.get('format')!r}, want {schema.FORMAT})"
        )
    arrays: dict[int, npt.NDArray[Any]] = {}
    for cid, chunks in parts.items():
        ch = channels[cid]
        dt = schema.dtype_from_json(ch.metadata["dtype"])
        arrays[cid] = np.frombuffer(b"".join(chunks), dtype=dt) if chunks else np.zeros(0, dt)
    # every stream holds the same blocks; a file cut inside a block's messages: keep the shortest
    n = min((a.size for a in arrays.values()), default=0)
    rec = Recording(p, meta, np.zeros(0, schema.cycle_dtype()), {}, {}, [], stats=stats, complete=complete)
    for cid, arr in arrays.items():
        ch = channels[cid]
        arr = arr[:n]
        if ch.topic == "/cycle":
            rec.cycles = arr
        elif ch.topic.startswith("/bus/"):
            rec.buses[ch.metadata["bus"]] = arr
            rec.slaves[ch.metadata["bus"]] = json.loads(ch.metadata["slaves"])
        elif ch.topic.startswith("/group/"):
            g = ch.metadata["group"]
            rec.groups[g] = arr
            rec.axes[g] = json.loads(ch.metadata["axes"])
            rec.units[g] = json.loads(ch.metadata["units"])
    last = int(rec.cycles["cycle"][-1]) if n else -1
    rec.events = sorted((e for e in events if e["cycle"] <= last), key=lambda e: e["cycle"])
    return rec
