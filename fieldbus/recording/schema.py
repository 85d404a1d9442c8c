"""What a recording holds: the numpy row types of its channels and their description in the file.

A recording is an MCAP file with one channel per stream:

- ``/cycle``: one row per cycle (:func:`cycle_dtype`);
- ``/bus/<bus>``: one row per cycle for each bus (:func:`bus_dtype`);
- ``/group/<group>``: one row per cycle for each axis group (:func:`group_dtype`):
  outputs (master -> drive) and inputs (drive -> master) of every axis in
  engineering units, optionally the wire bytes;
- ``/events``: one JSON message per event (:data:`EVENT_SCHEMA`).

Each numpy channel carries blocks of consecutive cycles: one MCAP message is
``rows * itemsize`` bytes, the rows of a packed little-endian structured
array. The schema record holds the dtype (``numpy.lib.format`` descr, as
JSON) and a description of every field; the channel metadata repeats the
dtype (``dtype``) and names the bus or group, its slaves and its axes.
"""

from __future__ import annotations

import copy
import json
from typing import Any

import numpy as np

from fieldbus.core.pdo.image import DirectionImage
from fieldbus.core.status_fields import NO_VALUE as NO_VALUE  # re-exported: the recording's readers use it
from fieldbus.core.status_fields import StatusField

FORMAT = "fieldbus.recording/1"  # bump on an incompatible change of the layout below (a column added is not)
SCHEMA_ENCODING = "numpy.dtype"  # schema data: JSON {"descr": ..., "fields": {name: description}}
MESSAGE_ENCODING = "numpy.rows"  # message data: packed little-endian rows of that dtype
# NO_VALUE (-2**63): int64 fields (DC time, wake-up latency) with no value in that cycle

CYCLE_FIELDS = {
    "cycle": "cycle index since bring-up (0 = the first exchange())",
    "t_ns": "start of exchange(), time.perf_counter_ns() (CLOCK_MONOTONIC on Linux), ns",
    "wakeup_ns": f"cycle start minus its deadline (run_cycles), ns; {NO_VALUE}: not measured",
    "exchange_ns": "time spent in exchange() (without the recording's copy), ns",
    "fresh": "every slave of every bus fresh",
    "safe_stop": "a safe stop is latched",
}

# what the bus columns mean; a BusStatus field not described here is described by its name
BUS_FIELDS = {
    "cycle": "cycle index",
    "ran": "the bus exchanged this cycle (a slower bus skips cycles)",
    "verdict": "0 OK, 1 SHORT (working counter off), 2 TIMEOUT (no reply)",
    "wkc": "working counter received (-1: none)",
    "consecutive_misses": "misses in a row up to this cycle",
    "safe_stop": "this bus latched a safe stop",
    "recovering": "a slave is being brought back to OP",
    "recoveries": "slaves / passes brought back to OP since bring-up (counter)",
    "errors": "cycles whose bus raised since bring-up (counter)",
    "release_pending": "clear_safe_stop() was asked; the latch opens after enough fresh cycles",
    "dc_time_ns": f"DC system time of this cycle's frame, ns; {NO_VALUE}: no DC",
    "dc_sync_error_ns": f"host phase error against the DC cycle, ns; {NO_VALUE}: no DC",
    "emergencies": "EMCY messages seen on this bus since bring-up (counter; -1: the bus has none)",
    "fresh": "per slave: inputs decoded this cycle",
    "nmt_state": "per node (CANopen): last heartbeat state byte, -1: none yet",
}

GROUP_FIELDS = {
    "cycle": "cycle index",
    "outputs": "per axis, master -> drive (RxPDO), engineering units (the drive map's unit); "
    "what exchange() encoded this cycle",
    "inputs": "per axis, drive -> master (TxPDO), engineering units; stale inputs hold their last good value",
    "outputs_wire": "per axis, the output bytes on the wire (raw recordings)",
    "inputs_wire": "per axis, the input bytes from the wire (raw recordings)",
}

# the file's column types where the type of the BusStatus field says too little (narrower than int64)
BUS_DTYPES = {"verdict": "u1", "wkc": "<i4", "consecutive_misses": "<u4", "recoveries": "<u4"}

EVENT_SCHEMA: dict[str, Any] = {
    "title": "fieldbus.recording event",
    "type": "object",
    "properties": {
        "cycle": {"type": "integer", "description": "cycle index at which it was seen"},
        "t_ns": {"type": "integer", "description": "that cycle's start, monotonic ns"},
        "kind": {
            "type": "string",
            "enum": [
                "safe_stop",
                "safe_stop_cleared",
                "recovery_started",
                "recovery_finished",
                "recovered",
                "recovery_error",
                "emcy",
                "nmt_state",
                "cia402_state",
                "sdo_abort",
                "drive_fault",
                "bus_error",
                "acyclic_error",
                "esc_errors",
                "link_down",
                "link_up",
                "output_clamp",
                "gap",
            ],
        },
        "bus": {"type": "string"},
        "group": {"type": "string"},
        "slave": {"type": "string", "description": "slave (axis) name, where the event is one slave's"},
        "old": {"type": ["string", "integer", "null"]},
        "new": {"type": ["string", "integer", "null"]},
        "detail": {"type": "string"},
        "axis": {"type": "integer", "description": "output_clamp: the row of the group's image"},
        "channel": {"type": "string", "description": "output_clamp: the output channel"},
        "asked": {"type": ["number", "string"], "description": "output_clamp: what the controller wrote"},
        "sent": {"type": "number", "description": "output_clamp: what went to the drive instead"},
        "access": {"enum": ["read", "write"], "description": "sdo_abort: the transfer asked for"},
        "index": {"type": "integer", "description": "sdo_abort: object index"},
        "sub_index": {"type": "integer", "description": "sdo_abort: object sub-index"},
        "code": {
            "type": ["integer", "null"],
            "description": "sdo_abort: the abort code (CiA 301 / ETG.1000.6); drive_fault: the error code 0x603F "
            "(null until read)",
        },
        "name": {
            "type": "string",
            "description": "sdo_abort: the abort code's name; drive_fault: the error's; output_clamp: the "
            "reason (NAN, INF, RANGE, STEP)",
        },
    },
    "required": ["cycle", "t_ns", "kind"],
}


def cycle_dtype(numbers: tuple[StatusField, ...] = ()) -> np.dtype[Any]:
    """The /cycle row: the cycle index, its start and wake-up latency, then each NUMBER field of the
    network's ``CycleResult`` (``numbers``: the ring's, derived from the dataclass)."""
    fields: list[tuple[Any, ...]] = [("cycle", "<u8"), ("t_ns", "<i8"), ("wakeup_ns", "<i8")]
    fields += [(f.name, "?" if f.flag and not f.optional else "<i8") for f in numbers]
    return np.dtype(fields)


def bus_dtype(n_slaves: int, *, nmt: bool, numbers: tuple[StatusField, ...]) -> np.dtype[Any]:
    """A bus's row: the cycle, each NUMBER field of its status (``numbers``, see
    :mod:`fieldbus.core.status_fields`), its EMCY count, the per-slave fresh flags (and NMT states)."""
    fields: list[tuple[Any, ...]] = [("cycle", "<u8")]
    for f in numbers:
        fields.append((f.name, BUS_DTYPES.get(f.name, "?" if f.flag and not f.optional else "<i8")))
    fields += [("emergencies", "<i8"), ("fresh", "?", (n_slaves,))]
    if nmt:
        fields.append(("nmt_state", "<i2", (n_slaves,)))
    return np.dtype(fields)


def bus_fields(dt: np.dtype[Any]) -> dict[str, str]:
    """What each field of the bus row ``dt`` means (:data:`BUS_FIELDS`; else ``BusStatus.<name>``)."""
    return {name: BUS_FIELDS.get(name, f"BusStatus.{name} (fieldbus.network)") for name in dt.names or ()}


def event_schema(texts: tuple[str, ...] = ()) -> dict[str, Any]:
    """:data:`EVENT_SCHEMA` with an event kind for each TEXT field of the bus status (``texts``)."""
    out: dict[str, Any] = copy.deepcopy(EVENT_SCHEMA)
    kinds = out["properties"]["kind"]["enum"]
    kinds += [t for t in texts if t not in kinds]
    return out


def packed(image: DirectionImage) -> np.dtype[Any]:
    """The channels of one direction as a packed little-endian dtype (no wire bytes, no padding)."""
    dt = image.values.dtype
    assert dt.names is not None
    return np.dtype([(name, dt.fields[name][0].newbyteorder("<")) for name in dt.names])  # type: ignore[index]


def group_dtype(outputs: DirectionImage, inputs: DirectionImage, *, raw: bool) -> np.dtype[Any]:
    n = outputs.n_axes
    fields: list[tuple[Any, ...]] = [
        ("cycle", "<u8"),
        ("outputs", packed(outputs), (n,)),
        ("inputs", packed(inputs), (n,)),
    ]
    if raw:
        fields += [
            ("outputs_wire", "u1", (n, outputs.layout.size)),
            ("inputs_wire", "u1", (n, inputs.layout.size)),
        ]
    return np.dtype(fields)


def dtype_to_json(dt: np.dtype[Any]) -> str:
    """The dtype as JSON (``numpy.lib.format.dtype_to_descr``); :func:`dtype_from_json` reads it back."""
    return json.dumps(np.lib.format.dtype_to_descr(dt))


def _tuples(descr: Any) -> Any:
    if isinstance(descr, str):
        return descr
    out = []
    for entry in descr:
        name, fmt, *shape = entry
        item: tuple[Any, ...] = (name, _tuples(fmt))
        if shape:
            item += (tuple(shape[0]),)
        out.append(item)
    return out


def dtype_from_json(text: str) -> np.dtype[Any]:
    return np.lib.format.descr_to_dtype(_tuples(json.loads(text)))


def schema_data(dt: np.dtype[Any], fields: dict[str, str]) -> bytes:
    """The schema record's data: the dtype and what each of its fields means."""
    names = dt.names or ()
    return json.dumps(
        {
            "format": FORMAT,
            "descr": json.loads(dtype_to_json(dt)),
            "byteorder": "little",
            "fields": {k: v for k, v in fields.items() if k in names},
        },
        indent=1,
    ).encode()
