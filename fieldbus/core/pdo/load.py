"""Drive-map YAML -> validated :class:`DriveMap`, with located errors.

Every problem is a :class:`~fieldbus.errors.PdoMapError` naming
``file:line:column`` and the field path. The accepted keys are a superset of
ethercat_driver_ros2's slave configuration files; see docs/yaml-reference.md.
"""

from __future__ import annotations

import difflib
import math
from collections.abc import Mapping
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from fieldbus.core import datatypes
from fieldbus.core.datatypes import DataType
from fieldbus.core.pdo.model import (
    CanopenConfig,
    CanopenPdo,
    Channel,
    DcMode,
    Direction,
    DriveMap,
    EthercatConfig,
    HomingConfig,
    MotionProfileConfig,
    OutputLimit,
    Pdo,
    SdoWrite,
    SyncManager,
    is_axis_object,
)
from fieldbus.core.pdo.names import CONTROLWORD, STATUSWORD, default_name
from fieldbus.core.yamlread import Reader
from fieldbus.core.yamlsrc import Located, PathT, format_path, load_file, load_located

if TYPE_CHECKING:
    from fieldbus.core.rawcan_config import RawCanConfig

CLASSIC_CAN_PDO_BYTES = 8
CAN_FD_PDO_BYTES = 64
COE_RANGES = {Direction.OUTPUTS: (0x1600, 0x17FF), Direction.INPUTS: (0x1A00, 0x1BFF)}
ANY_PDO_RANGE = (0x1600, 0x1BFF)  # a device with a fixed PDO assignment may name its PDOs anywhere here
# CiA 301 predefined connection set: default COB-IDs of PDO 1..4 (node id added).
DEFAULT_COB_IDS = {
    Direction.OUTPUTS: (0x200, 0x300, 0x400, 0x500),
    Direction.INPUTS: (0x180, 0x280, 0x380, 0x480),
}

_TOP_KEYS = (
    "name", "description", "vendor_id", "product_id", "revision", "profile",
    "assign_activate", "auto_fault_reset", "homing", "axes", "sdo", "rpdo", "tpdo", "sm", "ethercat", "canopen", "rawcan",
    "motion_profile", "limits",
)  # fmt: skip
_PDO_KEYS = ("index", "channels", "fixed", "name", "description")
_CHANNEL_KEYS = (
    "index", "sub_index", "type", "name", "command_interface", "state_interface",
    "default", "mask", "factor", "offset", "unit", "description", "safe_value",
)  # fmt: skip
_SDO_KEYS = ("index", "sub_index", "type", "value", "description")
_LIMIT_KEYS = ("min", "max", "max_step", "max_rate")
_HOMING_KEYS = ("method", "offset", "speeds", "acceleration", "timeout_ms")
_HOMING_SPEED_KEYS = ("switch", "zero")
_AXES_KEYS = ("count", "object_offsets", "pdo_offsets")
_SM_KEYS = ("index", "type", "pdo", "watchdog", "start", "size")
_ETHERCAT_KEYS = (
    "coe", "lrw", "mailbox_size", "sync0_shift_ns", "sync1_cycle_ns", "serial", "dc_modes", "pdo_assign",
    "diagnosis_history",
)  # fmt: skip
_DC_MODE_KEYS = (
    "name", "description", "assign_activate", "sync0_cycle_factor", "sync0_cycle_ns", "sync0_shift_ns",
    "sync1_cycle_factor", "sync1_cycle_ns", "sync1_shift_ns",
)  # fmt: skip
_CANOPEN_KEYS = ("fd", "heartbeat_ms", "disable_unused_pdos", "pdo")
_CANOPEN_PDO_KEYS = ("index", "cob_id", "cob_id_absolute", "transmission_type", "inhibit_time", "event_timer")
_PROFILES = ("cia402",)
# Top-level keys that only a drive map has: a file with none of them (or a near miss) is not one,
# and nothing of its content is quoted. Words as common as 'name', 'profile' do not count.
_MAP_MARKS = (
    "vendor_id", "product_id", "rpdo", "tpdo", "rawcan", "canopen", "ethercat", "assign_activate",
    "auto_fault_reset",
)  # fmt: skip
_MAP_MARKS_EXACT = ("sdo", "sm")


NOT_A_MAP = (
    "not a drive map: its top level is {shape}, with none of vendor_id, product_id, rpdo, tpdo, rawcan "
    "(its content is not shown)"
)


def looks_like_drive_map(data: Any) -> bool:
    """True when ``data`` (a loaded YAML document) is a mapping with a drive-map key or a near miss of one."""
    if not isinstance(data, Mapping):
        return False
    for key in data:
        if not isinstance(key, str) or len(key) > 40:
            continue
        if key in _MAP_MARKS_EXACT or difflib.get_close_matches(key.lower(), _MAP_MARKS, n=1, cutoff=0.75):
            return True
    return False


def shape(data: Any) -> str:
    """What a loaded document is, in words that quote none of it."""
    if data is None:
        return "empty"
    if isinstance(data, Mapping):
        return "a mapping"
    if isinstance(data, list):
        return "a list"
    if isinstance(data, str):
        return "a single string"
    return "a single value"


def load_drive_map(path: str | Path) -> DriveMap:
    """Load and validate the drive map at ``path``."""
    doc = load_file(path)
    return parse_drive_map(doc, default_name=Path(path).stem)


def drive_map_from_text(text: str, file: str = "<string>") -> DriveMap:
    """Validate a drive map given as YAML text (``file`` names it in errors)."""
    return parse_drive_map(load_located(text, file), default_name=Path(file).stem or "drive")


def parse_drive_map(doc: Located, default_name: str = "drive") -> DriveMap:
    """Validate a loaded document into a :class:`DriveMap`."""
    r = Reader(doc)
    if not looks_like_drive_map(doc.data):
        raise r.err((), NOT_A_MAP.format(shape=shape(doc.data)))
    top = r.mapping(doc.data, (), _TOP_KEYS)
    rawcan, raw_rpdo, raw_tpdo = _rawcan_frames(r, top)
    name = r.name(top["name"], ("name",)) if "name" in top else _safe_name(default_name)
    profile = r.choice(top["profile"], ("profile",), _PROFILES) if "profile" in top else None
    canopen_raw = top.get("canopen")
    canopen = _canopen(r, canopen_raw) if "canopen" in top else None
    can_pdos = _canopen_pdos(r, canopen_raw) if isinstance(canopen_raw, Mapping) else {}

    ethercat = _ethercat(r, top.get("ethercat"))
    if not ethercat.pdo_assign and canopen is not None:
        raise r.err(
            ("ethercat", "pdo_assign"),
            "a fixed PDO assignment takes PDO indexes as the device names them; "
            "a map with a canopen section needs the CiA 301 ranges (0x1600-0x17FF, 0x1A00-0x1BFF)",
        )
    if rawcan is not None:
        rpdo, tpdo = raw_rpdo, raw_tpdo
    else:
        rpdo = _pdos(r, top.get("rpdo"), Direction.OUTPUTS, canopen, can_pdos, ethercat.pdo_assign)
        tpdo = _pdos(r, top.get("tpdo"), Direction.INPUTS, canopen, can_pdos, ethercat.pdo_assign)
    if not isinstance(top.get("axes"), int | Mapping) or canopen is None:  # else checked after the axes
        _check_can_pdos(r, can_pdos, {p.index for p in (*rpdo, *tpdo)})

    sdos, homing, motion_profile = _startup_sdos(r, top)
    drive = DriveMap(
        name=name,
        vendor_id=r.integer(top.get("vendor_id", 0), ("vendor_id",), 0, 0xFFFFFFFF),
        product_id=r.integer(top.get("product_id", 0), ("product_id",), 0, 0xFFFFFFFF),
        revision=r.integer(top.get("revision", 0), ("revision",), 0, 0xFFFFFFFF),
        description=r.string(top.get("description", ""), ("description",)),
        profile=profile,
        assign_activate=r.integer(top.get("assign_activate", 0), ("assign_activate",), 0, 0xFFFF),
        auto_fault_reset=r.boolean(top.get("auto_fault_reset", False), ("auto_fault_reset",)),
        sdo=sdos,
        homing=homing,
        motion_profile=motion_profile,
        rpdo=rpdo,
        tpdo=tpdo,
        sm=_sync_managers(r, top.get("sm")),
        ethercat=ethercat,
        canopen=canopen,
        rawcan=rawcan,
        source=doc.file,
    )
    if "limits" in top:
        limits, off = _limits(r, top["limits"], drive)
        drive = replace(drive, limits=limits, limits_off=off)
    _check_dc_mode(r, drive)
    if "axes" in top:
        object_offsets, pdo_offsets = _axes(r, top["axes"], drive, canopen is not None)
        drive = replace(drive, object_offsets=object_offsets, pdo_offsets=pdo_offsets)
        if canopen is not None:
            drive = replace(drive, axis_canopen=_axis_canopen(r, drive, canopen, can_pdos))
            _check_can_pdos(r, can_pdos, {p.index for p in (*drive.bus_map.rpdo, *drive.bus_map.tpdo)})
    if profile == "cia402":
        if drive.find(Direction.OUTPUTS, CONTROLWORD) is None:
            raise r.err(("rpdo",), "profile cia402 needs the controlword 0x6040:00 in an rpdo")
        if drive.find(Direction.INPUTS, STATUSWORD) is None:
            raise r.err(("tpdo",), "profile cia402 needs the statusword 0x6041:00 in a tpdo")
    return drive


def _rawcan_frames(
    r: Reader, top: Mapping[Any, Any]
) -> tuple[RawCanConfig | None, tuple[Pdo, ...], tuple[Pdo, ...]]:
    """A rawcan map's ``rawcan:`` section (config, rpdo, tpdo: its frames), with none of the CoE keys;
    (None, (), ()) for a CoE map, which must then name its vendor and product ids."""
    if "rawcan" in top:
        from fieldbus.core.rawcan import parse_rawcan

        for key in ("rpdo", "tpdo", "sdo", "sm", "canopen", "ethercat", "homing", "motion_profile", "axes"):
            if key in top:
                raise r.err(
                    (key,), f"a rawcan map describes its frames under rawcan:, not with '{key}'", key=True
                )
        return parse_rawcan(r, top["rawcan"])
    for key in ("vendor_id", "product_id"):
        if key not in top:
            raise r.err((), f"missing required key '{key}'")
    return None, (), ()


def _startup_sdos(
    r: Reader, top: Mapping[Any, Any]
) -> tuple[tuple[SdoWrite, ...], HomingConfig | None, MotionProfileConfig | None]:
    """The start-up SDO writes: ``sdo:``, then those of ``homing:`` and ``motion_profile:`` (each returned too)."""
    sdos = _sdos(r, top.get("sdo"))
    homing = _homing(r, top["homing"], sdos) if "homing" in top else None
    if homing is not None:
        sdos = (*sdos, *homing_sdos(homing))
    motion_profile = _motion_profile(r, top["motion_profile"], sdos) if "motion_profile" in top else None
    if motion_profile is not None:
        sdos = (*sdos, *motion_profile_sdos(motion_profile))
    return sdos, homing, motion_profile


def _check_dc_mode(r: Reader, drive: DriveMap) -> None:
    """``assign_activate`` must be one of the device's ``ethercat.dc_modes`` when it lists any."""
    modes = drive.ethercat.dc_modes
    if modes and drive.assign_activate and all(m.assign_activate != drive.assign_activate for m in modes):
        offered = ", ".join(f"{m.name} 0x{m.assign_activate:04X}" for m in modes)
        raise r.err(
            ("assign_activate",),
            f"0x{drive.assign_activate:04X} is none of the device's ethercat.dc_modes ({offered})",
        )


def _limits(r: Reader, raw: Any, drive: DriveMap) -> tuple[tuple[OutputLimit, ...], bool]:
    """``limits:``: per output channel ``min``/``max`` (``max`` alone: -max..max), ``max_step`` per cycle,
    ``max_rate`` per second; or ``off`` (no window, no step: only the NaN and infinity rules)."""
    if raw is False or raw == "off":
        return (), True
    return parse_limits(r, raw, ("limits",), drive), False


def parse_limits(r: Reader, raw: Any, path: PathT, drive: DriveMap) -> tuple[OutputLimit, ...]:
    """A ``limits:`` mapping at ``path`` of ``r``'s file for ``drive``'s output channels (a map's own, or
    a network file's per-slave narrowing); errors name the file, line and field."""
    outputs = {c.name: c for c in drive.channels(Direction.OUTPUTS)}
    m = r.mapping(raw, path, outputs)
    out: list[OutputLimit] = []
    for name, item in m.items():
        cp: PathT = (*path, name)
        lm = r.mapping(item, cp, _LIMIT_KEYS)
        if not lm:
            raise r.err(cp, f"give {', '.join(_LIMIT_KEYS)} (or leave '{name}' out)")
        got = {k: r.number(v, (*cp, k)) for k, v in lm.items()}
        lo, hi = got.get("min"), got.get("max")
        if hi is not None and lo is None:
            if hi <= 0:
                raise r.err(
                    (*cp, "max"), f"max {hi:g} alone means -max..max: give a positive max, or a min too"
                )
            lo = -hi
        if lo is not None and hi is not None and not lo < hi:
            raise r.err((*cp, "max"), f"max {hi:g} must be greater than min {lo:g}")
        for key in ("max_step", "max_rate"):
            if key in got and not got[key] > 0:
                raise r.err((*cp, key), f"{key} must be greater than 0, not {got[key]:g}")
        ch = outputs[name]
        if not ch.scaled and not ch.type.is_float and lo is not None and hi is not None:
            for key, v in (("min", lo), ("max", hi)):
                if not ch.type.min <= v <= ch.type.max:
                    raise r.err(
                        (*cp, key if key in got else "max"),
                        f"{v:g} is outside what {ch.type.name} '{name}' holds ({ch.type.min:g}..{ch.type.max:g})",
                    )
        out.append(OutputLimit(name, lo, hi, got.get("max_step"), got.get("max_rate")))
    return tuple(out)


def _check_can_pdos(r: Reader, can_pdos: dict[int, tuple[int, PathT]], have: set[int]) -> None:
    for index, (_, path) in can_pdos.items():
        if index not in have:
            raise r.err(path, f"CANopen settings for PDO 0x{index:04X}, which is not in rpdo or tpdo")


def _axis_canopen(
    r: Reader, drive: DriveMap, canopen: CanopenConfig, can_pdos: dict[int, tuple[int, PathT]]
) -> tuple[tuple[int, CanopenPdo], ...]:
    """Axes 2..n's PDO copies' parameters: a ``canopen.pdo[]`` entry naming the copy's index, else axis 1's
    PDO's with CiA 301's pre-defined COB-ID of the copy's number (PDO 1-4), else an error naming the copy."""
    out: list[tuple[int, CanopenPdo]] = []
    for key, pdos, direction in (
        ("rpdo", drive.rpdo, Direction.OUTPUTS),
        ("tpdo", drive.tpdo, Direction.INPUTS),
    ):
        for i, p in enumerate(pdos):
            for k in range(1, drive.axes):
                index = p.index + drive.pdo_offsets[k]
                if index not in can_pdos and (index & 0x1FF) >= 4:
                    raise r.err(
                        (key, i, "index"),
                        f"axis {k + 1}'s copy of PDO 0x{p.index:04X} is 0x{index:04X}, "
                        f"{direction.yaml_key.upper()}{(index & 0x1FF) + 1}: only PDO 1-4 have a default "
                        f"COB-ID; give canopen.pdo[] {{index: 0x{index:04X}, cob_id: ...}}",
                    )
                params = _canopen_pdo_for(r, index, direction, canopen, can_pdos, (key, i))
                assert params is not None and p.canopen is not None
                if index not in can_pdos:  # axis 1's PDO's parameters, the copy's own default COB-ID
                    params = replace(p.canopen, cob_id=params.cob_id, cob_id_absolute=False)
                out.append((index, params))
    return tuple(out)


def _safe_name(stem: str) -> str:
    cleaned = "".join(ch if ch.isalnum() or ch in "_-." else "_" for ch in stem)
    return cleaned or "drive"


def _dtype(r: Reader, value: Any, path: PathT) -> DataType:
    text = r.string(value, path)
    dt = datatypes.lookup(text)
    if dt is None:
        near = datatypes.suggest(text)
        hint = f" (did you mean {near}?)" if near else f" (known: {', '.join(datatypes.TYPE_NAMES)})"
        raise r.err(path, f"unknown type '{text}'{hint}")
    return dt


def _pdos(
    r: Reader,
    raw: Any,
    direction: Direction,
    canopen: CanopenConfig | None,
    can_pdos: dict[int, tuple[int, PathT]],
    pdo_assign: bool = True,
) -> tuple[Pdo, ...]:
    key = direction.yaml_key
    lo, hi = COE_RANGES[direction] if pdo_assign else ANY_PDO_RANGE
    pdos: list[Pdo] = []
    seen_index: dict[int, int] = {}
    seen_names: dict[str, PathT] = {}
    bit_owner: dict[int, PathT] = {}  # absolute bit in the direction image -> channel path
    bit_cursor = 0
    for i, item in enumerate(r.sequence(raw, (key,))):
        ppath: PathT = (key, i)
        m = r.mapping(item, ppath, _PDO_KEYS, required=("index", "channels"))
        for text_key in ("name", "description"):  # documentation only, but checked like every key
            if text_key in m:
                r.string(m[text_key], (*ppath, text_key))
        index = r.integer(m["index"], (*ppath, "index"), 0, 0xFFFF)
        if not lo <= index <= hi:
            what = "RxPDO (master outputs)" if direction is Direction.OUTPUTS else "TxPDO (master inputs)"
            any_lo, any_hi = ANY_PDO_RANGE
            hint = " (fixed assignment? ethercat.pdo_assign: false)" if any_lo <= index <= any_hi else ""
            raise r.err(
                (*ppath, "index"), f"0x{index:04X} is not a {what} mapping index 0x{lo:04X}-0x{hi:04X}{hint}"
            )
        if index in seen_index:
            raise r.err(
                (*ppath, "index"), f"PDO 0x{index:04X} listed twice (also {key}[{seen_index[index]}])"
            )
        seen_index[index] = i
        channels: list[Channel] = []
        raw_channels = r.sequence(m["channels"], (*ppath, "channels"))
        if len(raw_channels) > 254:
            raise r.err(
                (*ppath, "channels"), f"{len(raw_channels)} entries; a mapping object holds at most 254"
            )
        for j, craw in enumerate(raw_channels):
            cpath: PathT = (*ppath, "channels", j)
            ch = _channel(r, craw, cpath, direction)
            _place_bits(r, ch, cpath, bit_cursor, bit_owner)
            bit_cursor += ch.bits
            if not ch.is_gap:
                if ch.name in seen_names:
                    other = seen_names[ch.name]
                    raise r.err(
                        (*cpath, "name") if "name" in craw else cpath,
                        f"duplicate {direction.value} channel name '{ch.name}' "
                        f"(also {format_path(other)}); give one a 'name'",
                    )
                seen_names[ch.name] = cpath
            channels.append(ch)
        pdo = Pdo(
            index=index,
            channels=tuple(channels),
            fixed=r.boolean(m.get("fixed", False), (*ppath, "fixed")),
            canopen=_canopen_pdo_for(r, index, direction, canopen, can_pdos, ppath),
        )
        if canopen is not None:
            limit = CAN_FD_PDO_BYTES if canopen.fd else CLASSIC_CAN_PDO_BYTES
            if pdo.size > limit:
                bus = "CAN FD" if canopen.fd else "classic CAN"
                raise r.err(
                    (*ppath, "channels"),
                    f"PDO 0x{index:04X} is {pdo.size} bytes; {bus} carries at most {limit} per PDO",
                )
            if len(channels) > 64:
                raise r.err((*ppath, "channels"), "a CANopen PDO maps at most 64 entries")
            if pdo.bits % 8:
                raise r.err(
                    (*ppath, "channels"),
                    f"PDO 0x{index:04X} is {pdo.bits} bits; on CANopen pad it to whole bytes with a bit{8 - pdo.bits % 8} gap",
                )
        pdos.append(pdo)
    return tuple(pdos)


def _channel(r: Reader, raw: Any, path: PathT, direction: Direction) -> Channel:
    m = r.mapping(raw, path, _CHANNEL_KEYS, required=("index", "sub_index", "type"))
    index = r.integer(m["index"], (*path, "index"), 0, 0xFFFF)
    sub = r.integer(m["sub_index"], (*path, "sub_index"), 0, 0xFF)
    dt = _dtype(r, m["type"], (*path, "type"))
    iface_key, interface = _channel_interface(r, m, path, direction)
    if index <= 0x0007:
        _check_gap(r, m, path, index, sub)
    if "name" in m:
        name = r.name(m["name"], (*path, "name"))
    elif interface:
        name = r.name(interface, (*path, iface_key))
    else:
        name = default_name(index, sub)
    mask = _mask(r, m, path, dt)
    default = _default(r, m, path, dt, direction)
    factor, offset, unit, scaled = _scaling(r, m, path, dt)
    safe_value = _safe_value(r, m, path, dt, direction, factor, offset, scaled)
    return Channel(
        index=index,
        sub_index=sub,
        type=dt,
        name=name,
        interface=interface,
        unit=unit,
        default=default,
        mask=mask,
        factor=factor,
        offset=offset,
        scaled=scaled,
        description=r.string(m.get("description", ""), (*path, "description")),
        safe_value=safe_value,
    )


def _channel_interface(
    r: Reader, m: Mapping[Any, Any], path: PathT, direction: Direction
) -> tuple[str, str | None]:
    """The channel's ros2_control interface key for its direction, and the interface it names (or None)."""
    wrong_iface = "state_interface" if direction is Direction.OUTPUTS else "command_interface"
    if wrong_iface in m:
        right = "command_interface" if direction is Direction.OUTPUTS else "state_interface"
        raise r.err(
            (*path, wrong_iface),
            f"{wrong_iface} belongs in the other direction; a {direction.yaml_key} channel uses {right}",
            key=True,
        )
    iface_key = "command_interface" if direction is Direction.OUTPUTS else "state_interface"
    return iface_key, r.string(m[iface_key], (*path, iface_key)) if iface_key in m else None


def _check_gap(r: Reader, m: Mapping[Any, Any], path: PathT, index: int, sub: int) -> None:
    """A gap entry (index 0..7: padding of its type's size) carries no name, interface, or value."""
    if index == 0 and sub != 0:
        raise r.err((*path, "sub_index"), "a gap (index 0) has sub_index 0")
    for k in (
        "name",
        "command_interface",
        "state_interface",
        "default",
        "factor",
        "offset",
        "unit",
        "safe_value",
    ):
        if k in m:
            raise r.err((*path, k), f"a gap entry (index 0x{index:04X}) carries no '{k}'", key=True)


def _mask(r: Reader, m: Mapping[Any, Any], path: PathT, dt: DataType) -> int | None:
    """A bool's ``mask``: the single bit of its byte it lives in (None: none given)."""
    if "mask" not in m:
        return None
    if dt.name != "bool":
        raise r.err((*path, "mask"), f"mask is only used with type bool, not {dt.name}", key=True)
    mask = r.integer(m["mask"], (*path, "mask"), 1, 0x80)
    if mask & (mask - 1):
        raise r.err((*path, "mask"), f"mask 0x{mask:02X} must be a single bit of the byte")
    return mask


def _default(
    r: Reader, m: Mapping[Any, Any], path: PathT, dt: DataType, direction: Direction
) -> float | None:
    """An output's ``default`` (raw value before the first command; NaN: none), checked against its type."""
    if "default" not in m:
        return None
    if direction is Direction.INPUTS:
        raise r.err((*path, "default"), "default is only for rpdo channels (master outputs)", key=True)
    d = r.number(m["default"], (*path, "default"), allow_nan=True)
    if math.isnan(d):
        return None
    if dt.is_bits and dt.name != "bool":
        ok = d == int(d) and 0 <= d < (1 << dt.bits)
    else:
        ok = dt.fits(d) if dt.name != "bool" else d in (0.0, 1.0)
    if not ok:
        raise r.err((*path, "default"), f"default {m['default']!r} does not fit {dt.name}")
    return d


def _scaling(
    r: Reader, m: Mapping[Any, Any], path: PathT, dt: DataType
) -> tuple[float, float, str | None, bool]:
    """``factor``, ``offset`` (raw = factor * value + offset), ``unit``, and whether any was given."""
    factor = r.number(m["factor"], (*path, "factor")) if "factor" in m else 1.0
    if factor == 0.0:
        raise r.err((*path, "factor"), "factor 0 would lose the value")
    if not math.isfinite(1.0 / factor):  # the codec divides by it (outputs) or by its inverse (inputs)
        raise r.err((*path, "factor"), f"factor {factor!r} is too small: 1/factor overflows a double")
    offset = r.number(m["offset"], (*path, "offset")) if "offset" in m else 0.0
    if not math.isfinite(offset / factor):
        raise r.err((*path, "offset"), f"offset {offset!r} / factor {factor!r} overflows a double")
    unit = r.string(m["unit"], (*path, "unit")) if "unit" in m else None
    scaled = any(k in m for k in ("factor", "offset", "unit"))
    if scaled and (dt.is_bits):
        raise r.err(path, f"factor/offset/unit need a numeric type, not {dt.name}")
    return factor, offset, unit, scaled


def _safe_value(
    r: Reader,
    m: Mapping[Any, Any],
    path: PathT,
    dt: DataType,
    direction: Direction,
    factor: float,
    offset: float,
    scaled: bool,
) -> float | None:
    """An output's ``safe_value`` (in the channel's unit), whose raw value must fit its type."""
    if "safe_value" not in m:
        return None
    if direction is Direction.INPUTS:
        raise r.err((*path, "safe_value"), "safe_value is only for rpdo channels (master outputs)", key=True)
    safe_value = r.number(m["safe_value"], (*path, "safe_value"))
    raw = factor * safe_value + offset if scaled else safe_value
    fits = (
        (raw in (0.0, 1.0) if dt.name == "bool" else 0 <= raw < (1 << dt.bits) and raw == int(raw))
        if dt.is_bits
        else dt.fits(raw)
    )
    if not fits:
        raise r.err((*path, "safe_value"), f"safe_value {safe_value:g} (raw {raw:g}) does not fit {dt.name}")
    return safe_value


def _place_bits(r: Reader, ch: Channel, path: PathT, cursor: int, owner: dict[int, PathT]) -> None:
    """Check that ``ch`` placed at bit ``cursor`` fits the process image rules."""
    byte, bit = divmod(cursor, 8)
    if ch.mask is not None:
        mask_bit = ch.mask.bit_length() - 1
        if mask_bit != bit:
            target = byte * 8 + mask_bit
            if target in owner:
                other = owner[target]
                raise r.err(
                    (*path, "mask"),
                    f"mask 0x{ch.mask:02X} overlaps bit {mask_bit} of byte {byte}, "
                    f"already used by {format_path(other)}",
                )
            raise r.err(
                (*path, "mask"),
                f"mask 0x{ch.mask:02X} does not match this entry's position "
                f"(bit {bit} of byte {byte}: mask 0x{1 << bit:02X}); add a bitN gap before it",
            )
    if not ch.type.is_bits and bit != 0 and (ch.type.is_float or ch.bits == 64):
        raise r.err(
            (*path, "type"),
            f"{ch.type.name} entry starts at bit {bit} of byte {byte}; it must start on a byte boundary",
        )
    for b in range(cursor, cursor + ch.bits):
        owner[b] = path


def _canopen(r: Reader, raw: Any) -> CanopenConfig:
    path: PathT = ("canopen",)
    if raw is None:
        return CanopenConfig()
    m = r.mapping(raw, path, _CANOPEN_KEYS)
    return CanopenConfig(
        fd=r.boolean(m.get("fd", False), (*path, "fd")),
        heartbeat_ms=r.integer(m.get("heartbeat_ms", 100), (*path, "heartbeat_ms"), 0, 0xFFFF),
        disable_unused_pdos=r.boolean(m.get("disable_unused_pdos", True), (*path, "disable_unused_pdos")),
    )


def _canopen_pdos(r: Reader, raw: Mapping[Any, Any]) -> dict[int, tuple[int, PathT]]:
    """Index -> (list position, path) of the entries in ``canopen.pdo``."""
    out: dict[int, tuple[int, PathT]] = {}
    for i, item in enumerate(r.sequence(raw.get("pdo"), ("canopen", "pdo"))):
        path: PathT = ("canopen", "pdo", i)
        m = r.mapping(item, path, _CANOPEN_PDO_KEYS, required=("index",))
        index = r.integer(m["index"], (*path, "index"), 0, 0xFFFF)
        if index in out:
            raise r.err((*path, "index"), f"CANopen settings for 0x{index:04X} given twice")
        out[index] = (i, path)
    return out


def _canopen_pdo_for(
    r: Reader,
    index: int,
    direction: Direction,
    canopen: CanopenConfig | None,
    can_pdos: dict[int, tuple[int, PathT]],
    pdo_path: PathT,
) -> CanopenPdo | None:
    if canopen is None:
        return None
    number = (index & 0x1FF) + 1
    defaults = DEFAULT_COB_IDS[direction]
    entry = can_pdos.get(index)
    m: Mapping[Any, Any] = {}
    path: PathT = pdo_path
    if entry is not None:
        path = entry[1]
        m = r.doc.data["canopen"]["pdo"][entry[0]]
    if "cob_id" in m:
        absolute = r.boolean(m.get("cob_id_absolute", False), (*path, "cob_id_absolute"))
        cob = r.integer(m["cob_id"], (*path, "cob_id"), 1, 0x7FF if absolute else 0x780)
    elif number <= 4:
        cob, absolute = defaults[number - 1], False
    else:
        raise r.err(
            (*pdo_path, "index"),
            f"PDO 0x{index:04X} is {direction.yaml_key.upper()}{number}: only PDO 1-4 have a default "
            "COB-ID; give canopen.pdo[].cob_id",
        )
    return CanopenPdo(
        cob_id=cob,
        cob_id_absolute=absolute,
        transmission_type=r.integer(m.get("transmission_type", 1), (*path, "transmission_type"), 0, 0xFF),
        inhibit_time=r.integer(m.get("inhibit_time", 0), (*path, "inhibit_time"), 0, 0xFFFF),
        event_timer=r.integer(m.get("event_timer", 0), (*path, "event_timer"), 0, 0xFFFF),
    )


def _sdos(r: Reader, raw: Any) -> tuple[SdoWrite, ...]:
    out = []
    for i, item in enumerate(r.sequence(raw, ("sdo",))):
        path: PathT = ("sdo", i)
        m = r.mapping(item, path, _SDO_KEYS, required=("index", "sub_index", "type", "value"))
        dt = _dtype(r, m["type"], (*path, "type"))
        value = r.number(m["value"], (*path, "value"))
        if dt.name == "bool":
            ok = value in (0.0, 1.0)
        elif dt.is_bits:
            ok = value == int(value) and 0 <= value < (1 << dt.bits)
        else:
            ok = dt.fits(value)
        if not ok:
            raise r.err((*path, "value"), f"value {m['value']!r} does not fit {dt.name}")
        out.append(
            SdoWrite(
                index=r.integer(m["index"], (*path, "index"), 0x1000, 0xFFFF),
                sub_index=r.integer(m["sub_index"], (*path, "sub_index"), 0, 0xFF),
                type=dt,
                value=value,
                description=r.string(m.get("description", ""), (*path, "description")),
            )
        )
    return tuple(out)


# -- homing: section ------------------------------------------------------------------------------

# CiA 402-2 (IEC 61800-7-201) homing methods: 1-14 and 17-30 with switches and/or index pulse, 33/34 index
# pulse only, 35 and 37 the current position (35 is 37's older number); 15, 16, 31, 32, 36 are reserved,
# negative numbers are the manufacturer's, 0 is "no homing"
HOMING_METHODS_STANDARD = frozenset((*range(1, 15), *range(17, 31), 33, 34, 35, 37))
HOMING_OBJECTS = (  # (index, sub, type, field) of the start-up SDOs, in the order bring-up writes them
    (0x6098, 0, "int8", "method"),
    (0x607C, 0, "int32", "offset"),
    (0x6099, 1, "uint32", "speeds.switch"),
    (0x6099, 2, "uint32", "speeds.zero"),
    (0x609A, 0, "uint32", "acceleration"),
)
U32_MAX = 0xFFFFFFFF


def _homing(r: Reader, raw: Any, sdos: tuple[SdoWrite, ...]) -> HomingConfig:
    path: PathT = ("homing",)
    m = r.mapping(raw, path, _HOMING_KEYS, required=("method",))
    method = r.integer(m["method"], (*path, "method"), -128, 127)
    if method >= 0 and method not in HOMING_METHODS_STANDARD:
        raise r.err(
            (*path, "method"),
            f"{method} is not a CiA 402 homing method (1-14, 17-30, 33, 34, 35, 37; negative numbers are "
            "the manufacturer's)",
        )
    speeds: Mapping[Any, Any] = {}
    if "speeds" in m:
        speeds = r.mapping(m["speeds"], (*path, "speeds"), _HOMING_SPEED_KEYS)
    cfg = HomingConfig(
        method=method,
        offset=r.integer(m.get("offset", 0), (*path, "offset"), -(2**31), 2**31 - 1),
        speed_switch=r.integer(speeds.get("switch", 0), (*path, "speeds", "switch"), 0, U32_MAX),
        speed_zero=r.integer(speeds.get("zero", 0), (*path, "speeds", "zero"), 0, U32_MAX),
        acceleration=r.integer(m.get("acceleration", 0), (*path, "acceleration"), 0, U32_MAX),
        timeout_ms=r.integer(m.get("timeout_ms", 30_000), (*path, "timeout_ms"), 1, 3_600_000),
    )
    for i, sdo in enumerate(sdos):
        for index, sub, _, field in HOMING_OBJECTS:
            if (sdo.index, sdo.sub_index) == (index, sub):
                raise r.err(
                    ("sdo", i, "index"),
                    f"0x{index:04X}:{sub:02X} is homing.{field}: set it in the homing section only",
                )
    return cfg


def homing_sdos(cfg: HomingConfig) -> tuple[SdoWrite, ...]:
    """The start-up SDO writes of a ``homing:`` section (0x6098, 0x607C, 0x6099:01/02, 0x609A)."""
    values = (cfg.method, cfg.offset, cfg.speed_switch, cfg.speed_zero, cfg.acceleration)
    out = []
    for (index, sub, tname, field), value in zip(HOMING_OBJECTS, values, strict=True):
        dt = datatypes.lookup(tname)
        assert dt is not None
        out.append(SdoWrite(index, sub, dt, float(value), description=f"homing.{field}"))
    return tuple(out)


# -- motion_profile: section (profile position / profile velocity) ------------------------------------

MOTION_PROFILE_OBJECTS = (  # (index, type, field) of the start-up SDOs, in the order bring-up writes them
    (0x6081, "uint32", "velocity"),
    (0x6083, "uint32", "acceleration"),
    (0x6084, "uint32", "deceleration"),
)
_MOTION_PROFILE_KEYS = ("velocity", "acceleration", "deceleration", "timeout_ms")


def _motion_profile(r: Reader, raw: Any, sdos: tuple[SdoWrite, ...]) -> MotionProfileConfig:
    path: PathT = ("motion_profile",)
    m = r.mapping(raw, path, _MOTION_PROFILE_KEYS)
    values = {
        field: r.integer(m[field], (*path, field), 1, U32_MAX) if field in m else None
        for _, _, field in MOTION_PROFILE_OBJECTS
    }
    for i, sdo in enumerate(sdos):
        for index, _, field in MOTION_PROFILE_OBJECTS:
            if (sdo.index, sdo.sub_index) == (index, 0):
                raise r.err(
                    ("sdo", i, "index"),
                    f"0x{index:04X}:00 is motion_profile.{field}: set it in the motion_profile section only",
                )
    return MotionProfileConfig(
        velocity=values["velocity"],
        acceleration=values["acceleration"],
        deceleration=values["deceleration"],
        timeout_ms=r.integer(m.get("timeout_ms", 30_000), (*path, "timeout_ms"), 1, 3_600_000),
    )


def motion_profile_sdos(cfg: MotionProfileConfig) -> tuple[SdoWrite, ...]:
    """The start-up SDO writes of a ``motion_profile:`` section (0x6081, 0x6083, 0x6084; the ones set)."""
    values = (cfg.velocity, cfg.acceleration, cfg.deceleration)
    out = []
    for (index, tname, field), value in zip(MOTION_PROFILE_OBJECTS, values, strict=True):
        if value is None:
            continue
        dt = datatypes.lookup(tname)
        assert dt is not None
        out.append(SdoWrite(index, 0, dt, float(value), description=f"motion_profile.{field}"))
    return tuple(out)


# -- axes: multi-axis devices -------------------------------------------------------------------------

MAX_AXES = 8  # CiA 402 logical devices 0x6000-0x67FF, 0x6800-0x6FFF, ... up to 0x9FFF
AXIS_OBJECT_STEP = 0x800  # CiA 402: the objects of logical device k sit 0x800 x k above the first's
AXIS_PDO_STEP = 0x10  # this project's default: axis k's PDOs at 0x1600 + 0x10 x k (0x1610, 0x1A10, ...)


def _axes(r: Reader, raw: Any, drive: DriveMap, canopen: bool) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """``axes: N`` or ``axes: {count, object_offsets, pdo_offsets}`` -> (object offsets, PDO offsets) per axis."""
    path: PathT = ("axes",)
    if isinstance(raw, Mapping):
        m = r.mapping(raw, path, _AXES_KEYS, required=("count",))
        count = r.integer(m["count"], (*path, "count"), 1, MAX_AXES)
    else:
        m, count = {}, r.integer(raw, path, 1, MAX_AXES)
    # CANopen: axis k's PDOs follow axis 1's in PDO number (2 RPDOs per axis: axis 2 has RPDO3-4), so
    # the first 4 + 4 PDOs keep CiA 301's pre-defined COB-IDs; EtherCAT: 0x10 apart (0x1600 -> 0x1610)
    pdo_step = max(len(drive.rpdo), len(drive.tpdo), 1) if canopen else AXIS_PDO_STEP
    offsets: list[tuple[int, ...]] = []
    for key, step, hi in (
        ("object_offsets", AXIS_OBJECT_STEP, 0x3800),
        ("pdo_offsets", pdo_step, 0x1FF),
    ):
        if key not in m:
            offsets.append(tuple(step * k for k in range(count)))
            continue
        items = r.sequence(m[key], (*path, key))
        if len(items) != count:
            raise r.err(
                (*path, key), f"{len(items)} offsets for {count} axes: give one per axis, the first 0"
            )
        got = tuple(r.integer(v, (*path, key, k), 0, hi) for k, v in enumerate(items))
        if got[0] != 0:
            raise r.err((*path, key, 0), "the first axis is the map's own objects: its offset is 0")
        for k, v in enumerate(got):
            if key == "object_offsets" and v % AXIS_OBJECT_STEP:
                raise r.err((*path, key, k), f"0x{v:X} is not a multiple of 0x800 (CiA 402 logical devices)")
            if v in got[:k]:
                raise r.err((*path, key, k), f"offset 0x{v:X} given twice: two axes would share it")
        offsets.append(got)
    object_offsets, pdo_offsets = offsets
    if count == 1:
        return object_offsets, pdo_offsets
    for key, pdos, direction in (
        ("rpdo", drive.rpdo, Direction.OUTPUTS),
        ("tpdo", drive.tpdo, Direction.INPUTS),
    ):
        hi = (COE_RANGES[direction] if drive.ethercat.pdo_assign else ANY_PDO_RANGE)[1]
        seen = {p.index for p in pdos}
        bits = sum(p.bits for p in pdos)
        if bits % 8:
            raise r.err(
                (key,), f"one axis's {key} is {bits} bits; with axes > 1 pad it to whole bytes (a bitN gap)"
            )
        for i, p in enumerate(pdos):
            for j, c in enumerate(p.channels):
                if not c.is_gap and not is_axis_object(c.index):
                    raise r.err(
                        (key, i, "channels", j, "index"),
                        f"0x{c.index:04X} is not a CiA 402 axis object (0x6000-0x67FF): with axes > 1 every "
                        "mapped object is repeated per axis",
                    )
            for k in range(1, count):
                index = p.index + pdo_offsets[k]
                if index > hi or index in seen:
                    why = "passes the PDO range" if index > hi else "is taken by another PDO of the device"
                    raise r.err(
                        (key, i, "index"), f"axis {k + 1}'s copy of PDO 0x{p.index:04X} (0x{index:04X}) {why}"
                    )
                seen.add(index)
    return object_offsets, pdo_offsets


def _sync_managers(r: Reader, raw: Any) -> tuple[SyncManager, ...]:
    out = []
    seen: set[int] = set()
    for i, item in enumerate(r.sequence(raw, ("sm",))):
        path: PathT = ("sm", i)
        m = r.mapping(item, path, _SM_KEYS, required=("index", "type"))
        index = r.integer(m["index"], (*path, "index"), 0, 15)
        if index in seen:
            raise r.err((*path, "index"), f"SyncManager {index} listed twice")
        seen.add(index)
        kind = r.choice(m["type"], (*path, "type"), ("output", "input"))
        pdo = m.get("pdo")
        if pdo is not None:
            pdo = r.choice(pdo, (*path, "pdo"), ("rpdo", "tpdo"))
            want = "output" if pdo == "rpdo" else "input"
            if kind != want:
                raise r.err((*path, "pdo"), f"{pdo} data needs an {want} SyncManager, this one is {kind}")
        wd = r.choice(m.get("watchdog", "disable"), (*path, "watchdog"), ("enable", "disable"))
        out.append(
            SyncManager(
                index=index,
                type=kind,
                pdo=pdo,
                watchdog=wd == "enable",
                start=r.integer(m["start"], (*path, "start"), 0, 0xFFFF) if "start" in m else None,
                size=r.integer(m["size"], (*path, "size"), 0, 0xFFFF) if "size" in m else None,
            )
        )
    return tuple(out)


def _ethercat(r: Reader, raw: Any) -> EthercatConfig:
    path: PathT = ("ethercat",)
    if raw is None:
        return EthercatConfig()
    m = r.mapping(raw, path, _ETHERCAT_KEYS)
    return EthercatConfig(
        coe=r.boolean(m.get("coe", True), (*path, "coe")),
        lrw=r.boolean(m.get("lrw", True), (*path, "lrw")),
        mailbox_size=r.integer(m.get("mailbox_size", 128), (*path, "mailbox_size"), 32, 1486),
        sync0_shift_ns=r.integer(m.get("sync0_shift_ns", 0), (*path, "sync0_shift_ns"), -(2**31), 2**31 - 1),
        sync1_cycle_ns=r.integer(m.get("sync1_cycle_ns", 0), (*path, "sync1_cycle_ns"), 0, 2**32 - 1),
        serial=r.integer(m.get("serial", 0), (*path, "serial"), 0, 0xFFFFFFFF),
        dc_modes=_dc_modes(r, m.get("dc_modes")),
        pdo_assign=r.boolean(m.get("pdo_assign", True), (*path, "pdo_assign")),
        diagnosis_history=r.boolean(m.get("diagnosis_history", False), (*path, "diagnosis_history")),
    )


def _dc_modes(r: Reader, raw: Any) -> tuple[DcMode, ...]:
    out: list[DcMode] = []
    seen: dict[str, int] = {}
    i32 = (-(2**31), 2**31 - 1)
    for i, item in enumerate(r.sequence(raw, ("ethercat", "dc_modes"))):
        path: PathT = ("ethercat", "dc_modes", i)
        m = r.mapping(item, path, _DC_MODE_KEYS, required=("name",))
        name = r.string(m["name"], (*path, "name"))
        if name in seen:
            raise r.err(
                (*path, "name"), f"DC mode '{name}' listed twice (also ethercat.dc_modes[{seen[name]}])"
            )
        seen[name] = i

        def num(key: str, lo: int, hi: int, p: PathT = path, mm: Mapping[Any, Any] = m) -> int:
            return r.integer(mm.get(key, 0), (*p, key), lo, hi)

        out.append(
            DcMode(
                name=name,
                description=r.string(m.get("description", ""), (*path, "description")),
                assign_activate=num("assign_activate", 0, 0xFFFF),
                sync0_cycle_factor=num("sync0_cycle_factor", *i32),
                sync0_cycle_ns=num("sync0_cycle_ns", 0, 2**32 - 1),
                sync0_shift_ns=num("sync0_shift_ns", *i32),
                sync1_cycle_factor=num("sync1_cycle_factor", *i32),
                sync1_cycle_ns=num("sync1_cycle_ns", 0, 2**32 - 1),
                sync1_shift_ns=num("sync1_shift_ns", *i32),
            )
        )
    return tuple(out)
