"""Network files: which drive map sits where, on which bus, at what cycle time.

Paths to maps are relative to the network file. A slave with ``count: N``
expands to N slaves; ``{i}`` in its name becomes 0..N-1 and a CAN ``node_id``
counts up from the one given. See docs/network-reference.md.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from fieldbus.core.emulator_opts import EmulatorOptions, parse_emulator
from fieldbus.core.liveness import unwatched_reason
from fieldbus.core.pdo.load import parse_drive_map
from fieldbus.core.pdo.model import DriveMap
from fieldbus.core.yamlread import Reader
from fieldbus.core.yamlsrc import Located, PathT, load_file, load_located

BUS_TYPES = ("ethercat", "canopen", "rawcan", "sim")
CAN_TYPES = ("canopen", "rawcan")
DEFAULT_CYCLE_US = 1000
DEFAULT_RECEIVE_TIMEOUT_US = (
    500  # legged-robot hardware tutorial §62.5: short receive timeout, reuse last data
)
DEFAULT_SAFE_STOP_AFTER = 10  # legged-robot hardware tutorial §62.5: safe stop after 10 consecutive misses

_TOP_KEYS = ("name", "cycle_time_us", "receive_timeout_us", "safe_stop_after", "buses")
_BUS_KEYS = (
    "name", "type", "interface", "redundant_interface", "can_interface", "can_options", "bitrate",
    "data_bitrate", "cycle_time_us", "receive_timeout_us", "safe_stop_after", "slaves",
)  # fmt: skip
_SLAVE_KEYS = ("name", "map", "node_id", "count", "position", "emulator")


@dataclass(frozen=True)
class Slave:
    """One drive on a bus: EtherCAT wire position (0-based) or CAN node id."""

    name: str
    map: DriveMap
    position: int
    node_id: int | None = None
    emulator: EmulatorOptions | None = None  # delays and imperfections of the emulated drive


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
        return self.type in CAN_TYPES


@dataclass(frozen=True)
class NetworkConfig:
    """A whole network file, maps loaded and validated."""

    name: str
    cycle_time_us: int
    buses: tuple[Bus, ...]
    source: str = "<string>"

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
    """True when a loaded YAML document looks like a network file (has ``buses``)."""
    return isinstance(data, dict) and "buses" in data


def parse_network(doc: Located, base: Path, default_name: str = "network") -> NetworkConfig:
    r = Reader(doc)
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
        bus = _bus(r, raw, ("buses", i), base, cache, cycle, timeout, stop_after)
        if bus.name in bus_names:
            raise r.err(("buses", i, "name"), f"duplicate bus name '{bus.name}'")
        bus_names.add(bus.name)
        buses.append(bus)
    name = r.name(top["name"], ("name",)) if "name" in top else default_name
    return NetworkConfig(name=name, cycle_time_us=cycle, buses=tuple(buses), source=doc.file)


def _bus(
    r: Reader,
    raw: Any,
    path: PathT,
    base: Path,
    cache: dict[Path, DriveMap],
    cycle: int,
    timeout: int,
    stop_after: int,
) -> Bus:
    m = r.mapping(raw, path, _BUS_KEYS, required=("name", "type", "slaves"))
    name = r.name(m["name"], (*path, "name"))
    kind = r.choice(m["type"], (*path, "type"), BUS_TYPES)
    is_can = kind in CAN_TYPES
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
    redundant = None
    if "redundant_interface" in m:
        if kind != "ethercat":
            raise r.err(
                (*path, "redundant_interface"),
                f"'redundant_interface' is for ethercat buses, this bus is {kind}",
                key=True,
            )
        redundant = r.string(m["redundant_interface"], (*path, "redundant_interface"))
        if redundant == m["interface"]:
            raise r.err(
                (*path, "redundant_interface"), f"the redundant port must be another card than '{redundant}'"
            )
    slaves: list[Slave] = []
    names: dict[str, PathT] = {}
    node_ids: dict[int, PathT] = {}
    raw_slaves = r.sequence(m["slaves"], (*path, "slaves"))
    if not raw_slaves:
        raise r.err((*path, "slaves"), "a bus needs at least one slave")
    for j, sraw in enumerate(raw_slaves):
        spath: PathT = (*path, "slaves", j)
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
            emu = parse_emulator(r, s["emulator"], (*spath, "emulator"), bus_cycle)
        if is_can:
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
        elif drive.rawcan is not None:
            raise r.err((*spath, "map"), f"map {drive.source} is a rawcan map; it needs a 'rawcan' bus")
        elif "node_id" in s:
            raise r.err((*spath, "node_id"), f"node_id is for CAN buses, this bus is {kind}", key=True)
        else:
            first = 0
        for k in range(count):
            sname = r.name(pattern.replace("{i}", str(k)), (*spath, "name"))
            if sname in names:
                raise r.err((*spath, "name"), f"duplicate slave name '{sname}' on bus '{name}'")
            names[sname] = spath
            node = first + k if is_can else None
            if node is not None:
                if node in node_ids:
                    raise r.err((*spath, "node_id"), f"node id {node} used twice on bus '{name}'")
                node_ids[node] = spath
            slaves.append(Slave(name=sname, map=drive, position=len(slaves), node_id=node, emulator=emu))
    return Bus(
        name=name,
        type=kind,
        slaves=tuple(slaves),
        cycle_time_us=r.integer(m.get("cycle_time_us", cycle), (*path, "cycle_time_us"), 50, 1_000_000),
        receive_timeout_us=r.integer(
            m.get("receive_timeout_us", timeout), (*path, "receive_timeout_us"), 10, 1_000_000
        ),
        safe_stop_after=r.integer(
            m.get("safe_stop_after", stop_after), (*path, "safe_stop_after"), 1, 100_000
        ),
        interface=r.string(m["interface"], (*path, "interface")) if "interface" in m else None,
        redundant_interface=redundant,
        can_options=_can_options(r, m.get("can_options"), (*path, "can_options")),
        can_interface=r.string(m.get("can_interface", "socketcan"), (*path, "can_interface"))
        if is_can
        else None,
        bitrate=bitrate,
        data_bitrate=data_bitrate,
    )


def _check_canopen_liveness(r: Reader, drive: DriveMap, path: PathT) -> None:
    """Refuse a CANopen node that could die unnoticed (no heartbeat, no TPDO with a deadline; see
    :mod:`fieldbus.core.liveness`), with the fix in the message."""
    assert drive.canopen is not None
    why = unwatched_reason(drive, drive.canopen.heartbeat_ms)
    if why is not None:
        raise r.err(path, f"map {drive.source}: {why}")


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


def _drive(r: Reader, raw: Any, path: PathT, base: Path, cache: dict[Path, DriveMap]) -> DriveMap:
    rel = r.string(raw, path)
    target = (base / rel).resolve()
    if target not in cache:
        if not target.is_file():
            raise r.err(path, f"map file not found: {rel} (looked for {target})")
        cache[target] = parse_drive_map(load_file(target), default_name=target.stem)
    return cache[target]
