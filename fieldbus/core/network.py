"""Network files: which drive map sits where, on which bus, at what cycle time.

Paths to maps are relative to the folder of the network file (absolute paths
work too); a map must be a ``.yaml``/``.yml`` regular file whose top level is a
drive map, and nothing of a file that is not one is quoted in an error. A slave
with ``count: N`` expands to N slaves; ``{i}`` in its name becomes 0..N-1 and a
CAN ``node_id`` counts up from the one given. What can never work is an error;
what may work but is likely a mistake is a warning in
:attr:`NetworkConfig.warnings`. See docs/network-reference.md.
"""

from __future__ import annotations

import difflib
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from fieldbus.core.base_config import parse_base
from fieldbus.core.diffdrive import DiffDriveParams
from fieldbus.core.emulator_opts import EmulatorSection, emulator_section
from fieldbus.core.liveness import unwatched_reason
from fieldbus.core.output_rules import widenings
from fieldbus.core.pdo.layout import layout
from fieldbus.core.pdo.load import (
    CLASSIC_CAN_PDO_BYTES,
    NOT_A_MAP,
    looks_like_drive_map,
    parse_drive_map,
    parse_limits,
    shape,
)
from fieldbus.core.pdo.model import DriveMap, OutputLimit
from fieldbus.core.yamlread import Reader
from fieldbus.core.yamlsrc import Located, PathT, load_file, load_located, token
from fieldbus.errors import FieldbusError, PdoMapError
from fieldbus.registry import BACKEND_OPTIONS, bus_type, bus_type_names

DEFAULT_CYCLE_US = 1000
DEFAULT_RECEIVE_TIMEOUT_US = (
    500  # legged-robot hardware tutorial §62.5: short receive timeout, reuse last data
)
DEFAULT_SAFE_STOP_AFTER = 10  # legged-robot hardware tutorial §62.5: safe stop after 10 consecutive misses

_TOP_KEYS = ("name", "cycle_time_us", "receive_timeout_us", "safe_stop_after", "buses", "base")
_BUS_KEYS = (
    "name", "type", "interface", "redundant_interface", "can_interface", "can_options", "bitrate",
    "data_bitrate", "cycle_time_us", "receive_timeout_us", "safe_stop_after", "slaves",
)  # fmt: skip
_SLAVE_KEYS = ("name", "map", "node_id", "count", "position", "emulator", "limits")
_NETWORK_MARKS = ("buses", "cycle_time_us", "receive_timeout_us", "safe_stop_after")
MAP_SUFFIXES = (".yaml", ".yml")
PATH_CHARS = 160  # most characters of a map path (from the network file) an error shows
SHIPPED_MAPS = Path(__file__).resolve().parents[1] / "pdo_maps"  # the drive maps shipped in the package
SHIPPED = "shipped:"  # ``map: shipped:NAME`` names the shipped map NAME(.yaml), wherever the network file is


@dataclass(frozen=True)
class Slave:
    """One drive on a bus: EtherCAT wire position (0-based) or CAN node id."""

    name: str
    map: DriveMap
    position: int
    node_id: int | None = None
    emulator: EmulatorSection | None = None  # the emulated drive's options, opaque (the emulator reads them)
    limits: tuple[OutputLimit, ...] = ()  # the network file's narrowing of the map's output limits


def row_names(slaves: Iterable[Slave]) -> tuple[str, ...]:
    """A name per row of a group's image: the slave's, or ``<slave>.axis<k>`` for each axis of a multi-axis one."""
    return tuple(
        s.name if s.map.axes == 1 else f"{s.name}.axis{k + 1}" for s in slaves for k in range(s.map.axes)
    )


@dataclass(frozen=True)
class Bus:
    """One bus. Times in µs; bit rates in bit/s (``data_bitrate`` only for CAN FD)."""

    name: str
    type: str
    slaves: tuple[Slave, ...]
    cycle_time_us: int
    receive_timeout_us: int
    safe_stop_after: int
    interface: str | None = None
    redundant_interface: str | None = None  # EtherCAT: SOEM's second port (cable redundancy)
    can_interface: str | None = None
    can_options: tuple[tuple[str, str | int | float | bool], ...] = ()  # more python-can Bus arguments
    bitrate: int | None = None
    data_bitrate: int | None = None

    @property
    def is_can(self) -> bool:
        return is_can_type(self.type)


@dataclass(frozen=True)
class NetworkConfig:
    """A whole network file, maps loaded and validated."""

    name: str
    cycle_time_us: int
    buses: tuple[Bus, ...]
    source: str = "<string>"
    warnings: tuple[str, ...] = ()
    """``file:line:column path: message`` of what may work but is likely a mistake (``fieldbus validate``
    prints them); e.g. a receive timeout longer than the cycle."""
    base: DiffDriveParams | None = None
    """A wheeled base on some of the joints (the ``base:`` section), if the file has one."""

    def bus(self, name: str) -> Bus:
        for b in self.buses:
            if b.name == name:
                return b
        raise KeyError(name)


def load_network(path: str | Path) -> NetworkConfig:
    """Load a network file and every drive map it names."""
    doc = load_file(path)
    return parse_network(doc, base=Path(path).parent, default_name=Path(path).stem)


def network_from_text(text: str, file: str = "<string>", base: str | Path = ".") -> NetworkConfig:
    return parse_network(load_located(text, file), base=Path(base), default_name=Path(file).stem)


def is_network_document(data: Any) -> bool:
    """True when a loaded YAML document looks like a network file: ``buses``, or a near miss of a key
    only a network file has (``busses``, ``cycle_time``)."""
    if not isinstance(data, Mapping):
        return False
    for key in data:
        near = (
            isinstance(key, str)
            and len(key) <= 40
            and difflib.get_close_matches(key.lower(), _NETWORK_MARKS, n=1, cutoff=0.75)
        )
        if near:
            return True
    return False


def parse_network(doc: Located, base: Path, default_name: str = "network") -> NetworkConfig:
    r = Reader(doc)
    if not is_network_document(doc.data):
        raise r.err(
            (),
            f"not a network file: its top level is {shape(doc.data)}, without 'buses' "
            "(its content is not shown)",
        )
    warnings: list[str] = []
    top = r.mapping(doc.data, (), _TOP_KEYS, required=("buses",))
    cycle = r.integer(top.get("cycle_time_us", DEFAULT_CYCLE_US), ("cycle_time_us",), 50, 1_000_000)
    timeout = r.integer(
        top.get("receive_timeout_us", DEFAULT_RECEIVE_TIMEOUT_US), ("receive_timeout_us",), 10, 1_000_000
    )
    stop_after = r.integer(
        top.get("safe_stop_after", DEFAULT_SAFE_STOP_AFTER), ("safe_stop_after",), 1, 100_000
    )
    cache: dict[Path, DriveMap] = {}
    buses: list[Bus] = []
    bus_names: set[str] = set()
    raw_buses = r.sequence(top["buses"], ("buses",))
    if not raw_buses:
        raise r.err(("buses",), "a network needs at least one bus")
    for i, raw in enumerate(raw_buses):
        bus = _bus(r, raw, ("buses", i), base, cache, cycle, timeout, stop_after, warnings)
        if bus.name in bus_names:
            raise r.err(("buses", i, "name"), f"duplicate bus name '{bus.name}'")
        bus_names.add(bus.name)
        buses.append(bus)
    name = r.name(top["name"], ("name",)) if "name" in top else default_name
    joints = [j for b in buses for j in row_names(b.slaves)]
    wheeled = parse_base(r, top["base"], ("base",), joints) if "base" in top else None
    return NetworkConfig(
        name=name,
        cycle_time_us=cycle,
        buses=tuple(buses),
        source=doc.file,
        warnings=tuple(warnings),
        base=wheeled,
    )


def _bus(
    r: Reader,
    raw: Any,
    path: PathT,
    base: Path,
    cache: dict[Path, DriveMap],
    cycle: int,
    timeout: int,
    stop_after: int,
    warnings: list[str],
) -> Bus:
    m = r.mapping(raw, path, _BUS_KEYS, required=("name", "type", "slaves"))
    name = r.name(m["name"], (*path, "name"))
    kind = r.choice(m["type"], (*path, "type"), bus_type_names())
    link = _bus_link(r, m, path, kind)
    slaves: list[Slave] = []
    names: dict[str, PathT] = {}
    node_ids: dict[int, PathT] = {}
    raw_slaves = r.sequence(m["slaves"], (*path, "slaves"))
    if not raw_slaves:
        raise r.err((*path, "slaves"), "a bus needs at least one slave")
    for j, sraw in enumerate(raw_slaves):
        spath: PathT = (*path, "slaves", j)
        for slave in _slave_entry(r, sraw, spath, m, path, kind, link, base, cache, cycle, len(slaves)):
            if slave.name in names:
                raise r.err((*spath, "name"), f"duplicate slave name '{slave.name}' on bus '{name}'")
            names[slave.name] = spath
            if slave.node_id is not None:
                if slave.node_id in node_ids:
                    raise r.err((*spath, "node_id"), f"node id {slave.node_id} used twice on bus '{name}'")
                node_ids[slave.node_id] = spath
            slaves.append(slave)
    bus_cycle = r.integer(m.get("cycle_time_us", cycle), (*path, "cycle_time_us"), 50, 1_000_000)
    bus_timeout = r.integer(
        m.get("receive_timeout_us", timeout), (*path, "receive_timeout_us"), 10, 1_000_000
    )
    if bus_timeout > bus_cycle:
        warnings.append(_late_reply_warning(r, m, path, name, bus_cycle, bus_timeout))
    return Bus(
        name=name,
        type=kind,
        slaves=tuple(slaves),
        cycle_time_us=bus_cycle,
        receive_timeout_us=bus_timeout,
        safe_stop_after=r.integer(
            m.get("safe_stop_after", stop_after), (*path, "safe_stop_after"), 1, 100_000
        ),
        interface=link.interface,
        redundant_interface=link.redundant,
        can_options=_can_options(r, m.get("can_options"), (*path, "can_options")),
        can_interface=link.can_interface,
        bitrate=link.bitrate,
        data_bitrate=link.data_bitrate,
    )


@dataclass(frozen=True)
class _Link:
    """How a bus reaches its wire: network card(s) for EtherCAT, CAN interface and bit rates for CAN."""

    is_can: bool
    interface: str | None
    redundant: str | None
    can_interface: str | None
    bitrate: int | None  # bit/s, CAN arbitration phase
    data_bitrate: int | None  # bit/s, CAN FD data phase


def _bus_link(r: Reader, m: Mapping[Any, Any], path: PathT, kind: str) -> _Link:
    """The bus's link keys, each checked against the bus type (CAN keys on a CAN bus only, and so on)."""
    is_can = is_can_type(kind)
    for key in ("can_interface", "can_options", "bitrate", "data_bitrate"):
        if key in m and not is_can:
            raise r.err((*path, key), f"'{key}' is for CAN buses, this bus is {kind}", key=True)
    bitrate = (
        r.integer(m.get("bitrate", 1_000_000), (*path, "bitrate"), 10_000, 1_000_000) if is_can else None
    )
    data_bitrate = (
        r.integer(m["data_bitrate"], (*path, "data_bitrate"), 10_000, 16_000_000)
        if "data_bitrate" in m
        else None
    )
    if kind in ("ethercat",) and "interface" not in m:
        raise r.err(path, "an ethercat bus needs 'interface' (the network card, e.g. eth0)")
    interface = _interface(r, m, (*path, "interface"), kind) if "interface" in m else None
    can_interface = (
        _can_interface(r, m.get("can_interface", "socketcan"), (*path, "can_interface")) if is_can else None
    )
    redundant = None
    if "redundant_interface" in m:
        if kind != "ethercat":
            raise r.err(
                (*path, "redundant_interface"),
                f"'redundant_interface' is for ethercat buses, this bus is {kind}",
                key=True,
            )
        redundant = _interface(r, m, (*path, "redundant_interface"), kind)
        if redundant == m["interface"]:
            raise r.err(
                (*path, "redundant_interface"), f"the redundant port must be another card than '{redundant}'"
            )
    return _Link(is_can, interface, redundant, can_interface, bitrate, data_bitrate)


def _slave_entry(
    r: Reader,
    sraw: Any,
    spath: PathT,
    m: Mapping[Any, Any],
    path: PathT,
    kind: str,
    link: _Link,
    base: Path,
    cache: dict[Path, DriveMap],
    cycle: int,
    start: int,
) -> Iterator[Slave]:
    """One entry of ``slaves:``: ``count`` slaves of one map from wire position ``start``, names from ``{i}``.

    The entry is read whole first; each slave is named as the bus takes it (so the bus checks each name
    for a duplicate before the next is read).
    """
    s = r.mapping(sraw, spath, _SLAVE_KEYS, required=("name", "map"))
    if "position" in s:
        raise r.err(
            (*spath, "position"), "EtherCAT slaves are listed in wire order; drop 'position'", key=True
        )
    count = r.integer(s.get("count", 1), (*spath, "count"), 1, 1024)
    pattern = r.string(s["name"], (*spath, "name"))
    if count > 1 and "{i}" not in pattern:
        raise r.err((*spath, "name"), f"count: {count} needs '{{i}}' in the name to keep names unique")
    drive = _drive(r, s["map"], (*spath, "map"), base, cache)
    emu = None
    if "emulator" in s:
        bus_cycle = r.integer(m.get("cycle_time_us", cycle), (*path, "cycle_time_us"), 50, 1_000_000)
        emu = emulator_section(r, s["emulator"], (*spath, "emulator"), bus_cycle)
        _check_emulator(emu)
    first = _first_node_id(r, s, spath, m, kind, link, drive, count)
    narrow: tuple[OutputLimit, ...] = ()
    if "limits" in s:
        bus_cycle = r.integer(m.get("cycle_time_us", cycle), (*path, "cycle_time_us"), 50, 1_000_000)
        narrow = _slave_limits(r, s["limits"], (*spath, "limits"), drive, bus_cycle / 1e6, link.is_can)
    for k in range(count):
        sname = r.name(pattern.replace("{i}", str(k)), (*spath, "name"))
        node = first + k if link.is_can else None
        yield Slave(name=sname, map=drive, position=start + k, node_id=node, emulator=emu, limits=narrow)


def _first_node_id(
    r: Reader,
    s: Mapping[Any, Any],
    spath: PathT,
    m: Mapping[Any, Any],
    kind: str,
    link: _Link,
    drive: DriveMap,
    count: int,
) -> int:
    """The entry's first CAN node id (0 off CAN), and its map checked against the bus type."""
    if link.is_can:
        if "node_id" not in s:
            raise r.err(spath, "a CAN slave needs 'node_id'")
        first = r.integer(s["node_id"], (*spath, "node_id"), 1, 127)
        if first + count - 1 > 127:
            raise r.err((*spath, "count"), f"node ids {first}..{first + count - 1} pass 127")
        if kind == "canopen" and drive.canopen is None:
            raise r.err((*spath, "map"), f"map {drive.source} has no 'canopen' section")
        if kind == "canopen":
            _check_canopen_liveness(r, drive, (*spath, "map"))
        if kind == "rawcan" and drive.rawcan is None:
            raise r.err((*spath, "map"), f"map {drive.source} has no 'rawcan' section")
        if kind == "canopen" and link.data_bitrate is None and not _fd_option(m.get("can_options")):
            _classic_frames_only(r, drive, (*spath, "map"))
        return first
    if drive.rawcan is not None:
        raise r.err((*spath, "map"), f"map {drive.source} is a rawcan map; it needs a 'rawcan' bus")
    if "node_id" in s:
        raise r.err((*spath, "node_id"), f"node_id is for CAN buses, this bus is {kind}", key=True)
    return 0


def _late_reply_warning(
    r: Reader, m: Mapping[Any, Any], path: PathT, name: str, bus_cycle: int, bus_timeout: int
) -> str:
    """The warning for a receive timeout (us) longer than the bus's cycle (us), at the key that set it."""
    where: PathT = (
        (*path, "receive_timeout_us")
        if "receive_timeout_us" in m
        else ("receive_timeout_us",)
        if "receive_timeout_us" in r.doc.data
        else path
    )
    default = "" if "receive_timeout_us" in m or "receive_timeout_us" in r.doc.data else " (the default)"
    return str(
        r.err(
            where,
            f"bus '{name}': receive_timeout_us {bus_timeout}{default} is longer than its cycle "
            f"({bus_cycle} us): a lost reply makes that cycle late by up to "
            f"{bus_timeout - bus_cycle} us",
        )
    )


def _check_emulator(section: EmulatorSection) -> None:
    """The emulators' check of an ``emulator:`` section (fieldbus.emulators); none installed: accepted."""
    from fieldbus.emulators import emulator_options_check

    check = emulator_options_check()
    if check is not None:
        check(section)


def _slave_limits(
    r: Reader, raw: Any, path: PathT, drive: DriveMap, cycle_s: float, is_can: bool
) -> tuple[OutputLimit, ...]:
    """A slave's ``limits:`` (the map's keys, per output channel): narrowing the map's only; a value that
    would widen them is an error naming its line and key."""
    narrow = parse_limits(r, raw, path, drive)
    lay = layout(drive, pdo_align=8 if is_can else 1).outputs
    for channel, key, why in widenings(drive, lay, cycle_s, narrow):
        given = raw.get(channel) if isinstance(raw, Mapping) else None
        where = key if not isinstance(given, Mapping) or key in given else "max"
        raise r.err((*path, channel, where), why)
    return narrow


def _check_canopen_liveness(r: Reader, drive: DriveMap, path: PathT) -> None:
    """Refuse a CANopen node that could die unnoticed (no heartbeat, no TPDO with a deadline; see
    :mod:`fieldbus.core.liveness`), with the fix in the message."""
    assert drive.canopen is not None
    why = unwatched_reason(drive, drive.canopen.heartbeat_ms)
    if why is not None:
        raise r.err(path, f"map {drive.source}: {why}")


def _interface(r: Reader, m: Mapping[Any, Any], path: PathT, kind: str) -> str:
    """A network card or CAN channel name: not empty, no spaces at either end."""
    text = r.string(m[path[-1]], path)
    if not text.strip():
        what = "network card (e.g. eth0)" if kind == "ethercat" else "CAN channel (e.g. can0)"
        raise r.err(path, f"empty: name the {what}")
    if text != text.strip() or not text.isprintable():
        raise r.err(path, f"'{token(text)}' has spaces at an end or unprintable characters")
    return text


def known_can_interfaces() -> frozenset[str] | None:
    """python-can's interface names (its own and plugins'), or None when python-can is not installed."""
    try:
        from can.interfaces import VALID_INTERFACES
    except ImportError:
        return None
    return frozenset(VALID_INTERFACES)


def _can_interface(r: Reader, raw: Any, path: PathT) -> str:
    text = r.string(raw, path)
    known = known_can_interfaces()
    if known is not None and text not in known:
        near = difflib.get_close_matches(token(text), sorted(known), n=1, cutoff=0.6)
        hint = f" (did you mean {near[0]}?)" if near else f" (known: {', '.join(sorted(known))})"
        raise r.err(path, f"python-can has no interface '{token(text)}'{hint}")
    return text


def _fd_option(raw: Any) -> bool:
    return isinstance(raw, Mapping) and raw.get("fd") is True


def _classic_frames_only(r: Reader, drive: DriveMap, path: PathT) -> None:
    """A CANopen bus without ``data_bitrate`` (or ``can_options: {fd: true}``) is classic CAN: 8-byte frames."""
    for key, pdos in (("rpdo", drive.rpdo), ("tpdo", drive.tpdo)):
        for pdo in pdos:
            if pdo.size > CLASSIC_CAN_PDO_BYTES:
                raise r.err(
                    path,
                    f"{key} 0x{pdo.index:04X} of map {drive.name} is {pdo.size} bytes and this bus is classic "
                    f"CAN ({CLASSIC_CAN_PDO_BYTES} bytes a frame): give the bus a data_bitrate for CAN FD",
                )


def is_can_type(kind: str) -> bool:
    """Whether bus type ``kind`` is a CAN bus (as its backend declares, :mod:`fieldbus.registry`)."""
    declared = bus_type(kind)
    return declared is not None and declared.can


def backend_options(kind: str) -> tuple[str, ...] | None:
    """The ``open_network(**options)`` names the backend of ``kind`` declares; None: it takes any."""
    declared = bus_type(kind)
    return None if declared is None else declared.options


def check_backend_options(kinds: Iterable[str], options: Iterable[str]) -> None:
    """Refuse an option that none of the backends ``kinds`` reads, with a did-you-mean.

    ``kinds`` are the backends that receive ``options`` (a network's bus types, or the ``backend=``
    override). A kind whose backend declares no options (an entry-point backend without
    ``bus_options``) accepts anything.
    """
    accepted: set[str] = set()
    for kind in kinds:
        names = backend_options(kind)
        if names is None:
            return
        accepted.update(names)
    for option in options:
        if option not in accepted:
            every = sorted({n for names in BACKEND_OPTIONS.values() for n in names})
            near = difflib.get_close_matches(option, sorted(accepted) or every, n=1, cutoff=0.6)
            hint = f"; did you mean {near[0]}?" if near else ""
            which = ", ".join(sorted(set(kinds)))
            have = ", ".join(sorted(accepted)) or "none"
            other = [k for k, names in BACKEND_OPTIONS.items() if option in names]
            also = f"; {option!r} is for the {' / '.join(other)} backend" if other else ""
            raise FieldbusError(
                f"unknown option {option!r} for the {which} backend{hint} (it takes: {have}{also})"
            )


def _can_options(r: Reader, raw: Any, path: PathT) -> tuple[tuple[str, str | int | float | bool], ...]:
    """``can_options``: keyword arguments for python-can's ``Bus`` (e.g. ``{port: 43114}``), scalars only."""
    if raw is None:
        return ()
    m = r.mapping(raw, path, [k for k in raw if isinstance(k, str)] if isinstance(raw, dict) else ())
    out = []
    for key, value in m.items():
        if key in ("interface", "channel", "bitrate", "data_bitrate"):
            raise r.err(
                (*path, key),
                f"'{key}' is set by the bus itself (can_interface, interface, bitrate)",
                key=True,
            )
        if not isinstance(value, (str, int, float, bool)):
            raise r.err((*path, key), "expected a number, a string or true/false")
        out.append((str(key), value))
    return tuple(out)


def check_open_options(
    net: NetworkConfig,
    backend: str | None,
    backend_options: Mapping[str, object],
    bus_options: Mapping[str, Mapping[str, object]] | None = None,
) -> None:
    """Refuse ``open_network`` options that no backend of ``net`` reads (``backend`` overrides the types).

    Shared ``backend_options`` must be read by the backend of at least one bus; ``bus_options[name]``
    by that bus's backend. Raises :class:`FieldbusError` with a did-you-mean.
    """
    check_backend_options({backend or b.type for b in net.buses}, backend_options)
    for bus in net.buses:
        check_backend_options((backend or bus.type,), (bus_options or {}).get(bus.name, {}))


def shipped_map_names() -> list[str]:
    """The names of the drive maps shipped in the package (``map: shipped:NAME``), sorted."""
    return sorted(f.stem for f in SHIPPED_MAPS.glob("*.yaml"))


def _shipped(r: Reader, rel: str, path: PathT) -> str:
    """The file name of the shipped map ``shipped:NAME`` names (``.yaml`` optional), else refused."""
    name = rel[len(SHIPPED) :].strip()
    stem = name[: -len(Path(name).suffix)] if Path(name).suffix.lower() in MAP_SUFFIXES else name
    if stem not in shipped_map_names():
        close = difflib.get_close_matches(stem, shipped_map_names(), n=1)
        hint = f"did you mean '{SHIPPED}{close[0]}'? " if close else ""
        raise r.err(
            path,
            f"no shipped drive map '{token(name, PATH_CHARS)}': {hint}the shipped maps are "
            + ", ".join(shipped_map_names()),
        )
    return f"{stem}.yaml"


def _shipped_hint(name: str) -> str:
    """For a map file not found: how to name the shipped map of that name, or that shipped maps exist."""
    stem = Path(name).stem
    if stem in shipped_map_names():
        return f"; the map shipped in the package is 'map: {SHIPPED}{stem}'"
    return f"; a map shipped in the package is named 'map: {SHIPPED}NAME' (fieldbus.PDO_MAPS)"


def _drive(r: Reader, raw: Any, path: PathT, base: Path, cache: dict[Path, DriveMap]) -> DriveMap:
    """The drive map at ``raw``: relative to ``base`` (the network file's folder), absolute, or
    ``shipped:NAME``, a map shipped in the package (:data:`fieldbus.PDO_MAPS`, no path needed).

    Refused before it is read: a path that does not end in .yaml/.yml, a directory, a missing file,
    a symbolic-link loop. Read, it must look like a drive map, else its content is not quoted.
    """
    rel = r.string(raw, path)
    if not rel.strip():
        raise r.err(path, "empty: give the drive map's path, relative to this file")
    if rel.startswith(SHIPPED):
        rel, base = _shipped(r, rel, path), SHIPPED_MAPS
    if Path(rel).suffix.lower() not in MAP_SUFFIXES:
        raise r.err(
            path, f"'{token(rel, PATH_CHARS)}' is not a drive map: a map's file name ends in .yaml or .yml"
        )
    try:
        target = (base / rel).resolve()
    except (RuntimeError, OSError):  # Python < 3.13: RuntimeError on a symlink loop
        raise r.err(path, f"map path {token(rel, PATH_CHARS)}: a symbolic link loop") from None
    if target not in cache:
        if target.is_dir():
            raise r.err(path, f"map path {token(rel, PATH_CHARS)} is a directory, not a drive map")
        if not target.exists():
            raise r.err(path, f"map file not found: {rel} (looked for {target}){_shipped_hint(target.name)}")
        try:
            doc = load_file(target)
        except PdoMapError as exc:
            if exc.line is not None:  # a YAML syntax error: where it is in the map
                raise
            raise r.err(
                path, f"map {token(rel, PATH_CHARS)}: {exc.message}"
            ) from None  # unreadable, not text
        if not looks_like_drive_map(doc.data):
            raise r.err(path, f"map {token(rel, PATH_CHARS)}: " + NOT_A_MAP.format(shape=shape(doc.data)))
        cache[target] = parse_drive_map(doc, default_name=target.stem)
    return cache[target]
