"""ODrive controllers on CAN (CANSimple): the family's protocol as data (a drive map's ``rawcan.odrive``) and its codec.

Pure: no I/O. The facts the maps declare (cited in ``docs/can-actuators.md``; the DBC files
``odrive-cansimple-0.5.6.dbc`` / ``-0.6.10.dbc`` odriverobotics publishes, shipped in the ``odrive-can``
package, are the reference the tests decode with):

- an 11-bit arbitration id is ``node << 5 | command``; every number is little-endian;
- the master asks for a message with a remote (RTR) frame on its id; the controller answers on the same id;
- the heartbeat (command 0x01, at the controller's own rate): axis error (uint32 bit flags), axis state
  (uint8; 1 IDLE, 8 CLOSED_LOOP_CONTROL);
- Set_Axis_State 0x07 (uint32), Set_Controller_Mode 0x0B (uint32 control mode, uint32 input mode),
  Set_Input_Pos 0x0C (float32 turns, int16 velocity feed-forward x 0.001 turn/s, int16 torque
  feed-forward x 0.001 N·m), Set_Input_Vel 0x0D (float32 turn/s, float32 N·m), Set_Input_Torque 0x0E
  (float32 N·m), Get_Encoder_Estimates 0x09 (float32 turns, float32 turn/s), Reboot 0x16, Clear_Errors 0x18;
- firmware 0.6 (Pro, S1, Micro) adds Get_Error 0x03 (uint32 active errors, uint32 disarm reason),
  RxSdo 0x04 / TxSdo 0x05 (endpoint access: opcode, uint16 endpoint, reserved, 4 value bytes) and
  Address 0x06, where 0.5 (ODrive 3.6) has Get_Motor_Error 0x03, Get_Encoder_Error 0x04,
  Get_Sensorless_Error 0x05 and Set_Axis_Node_ID 0x06.
"""

from __future__ import annotations

import struct
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from fieldbus.core.yamlsrc import PathT

ODRIVE_KEYS = (
    "protocol", "commands", "mode", "modes", "states", "errors", "watchdog_ms", "heartbeat_ms", "config",
    "state_field", "error_field", "request_field", "clear",
)  # fmt: skip
MODE_KEYS = ("name", "command", "control_mode", "input_mode", "fields")
SETPOINT_KEYS = ("from", "type", "scale")
SETPOINT_TYPES = {"float32": ("<f", 4), "int16": ("<h", 2)}  # int16: the feed-forwards of Set_Input_Pos
CONFIG_KEYS = ("name", "endpoint", "type", "value")
CONFIG_TYPES = {"float32": "<f", "uint32": "<I", "int32": "<i", "bool": "<I"}
STATE_KEYS = ("idle", "closed_loop")
# the commands every table has, and those only one firmware line has (odriverobotics' DBC files)
COMMON = (
    "heartbeat", "set_axis_state", "get_encoder_estimates", "set_controller_mode", "set_input_pos",
    "set_input_vel", "set_input_torque", "reboot", "clear_errors",
)  # fmt: skip
ONLY = {
    "0.5": ("get_motor_error", "get_encoder_error", "get_sensorless_error", "set_axis_node_id"),
    "0.6": ("get_error", "rxsdo", "txsdo", "address"),
}
SDO_READ, SDO_WRITE = 0, 1  # RxSdo opcodes


@dataclass(frozen=True)
class SetpointField:
    """One number of a set-point frame: ``raw = value * scale`` of command field ``source`` (an int16
    saturates at -32768..32767, NaN sends 0). ``at``: the source's byte offset in the image's output row
    (its wire bytes, little-endian: a float32, or an integer of ``source_bytes`` bytes, signed or not)."""

    source: str
    type: str  # float32 | int16
    scale: float = 1.0
    at: int = 0
    source_type: str = "float32"  # float32 | int | uint
    source_bytes: int = 4


@dataclass(frozen=True)
class OdriveMode:
    """A controller mode: Set_Controller_Mode values and the set-point command whose frame carries it."""

    name: str
    command: int  # the command id of the set-point (0x0C, 0x0D, 0x0E)
    control_mode: int
    input_mode: int
    fields: tuple[SetpointField, ...]


@dataclass(frozen=True)
class ConfigItem:
    """An endpoint written at bring-up through RxSdo and read back (firmware 0.6)."""

    name: str
    endpoint: int
    type: str
    value: float


@dataclass(frozen=True)
class OdriveProtocol:
    """An ODrive map's family section."""

    protocol: str  # "0.5" | "0.6"
    commands: Mapping[str, int]
    modes: tuple[OdriveMode, ...]
    mode: str
    idle: int
    closed_loop: int
    errors: tuple[tuple[int, str], ...]  # (bit mask, name) of the heartbeat's axis error
    watchdog_ms: float  # what the map's config sets (0: not set over CAN; see the docs)
    heartbeat_ms: float
    config: tuple[ConfigItem, ...]
    request_field: str  # command channel whose value is the requested axis state (0: none)
    request_at: tuple[int, int]  # its byte offset and size in the output row (unsigned little-endian)
    state_field: str  # reply channel holding the heartbeat's axis state
    error_field: str  # reply channel holding the heartbeat's axis error
    clear: bytes

    def can_id(self, node: int, command: str) -> int:
        return node << 5 | self.commands[command]

    def mode_named(self, name: str) -> OdriveMode:
        for m in self.modes:
            if m.name == name:
                return m
        raise KeyError(name)

    def error_names(self, flags: int) -> str:
        """The names of the bits set in ``flags`` ("none" for 0), unknown bits as hex."""
        names = [n for bit, n in self.errors if flags & bit]
        rest = flags & ~sum(bit for bit, _ in self.errors)
        if rest:
            names.append(f"0x{rest:X}")
        return ", ".join(names) or "none"


def parse_odrive(r: Any, raw: Any, path: PathT, command: Any, reply: Any) -> OdriveProtocol:
    """Validate ``rawcan.odrive`` (``command``/``reply``: the image's fields)."""
    m: Mapping[Any, Any] = r.mapping(
        raw, path, ODRIVE_KEYS, required=("protocol", "commands", "modes", "states", "errors")
    )
    version = r.choice(str(m["protocol"]), (*path, "protocol"), tuple(ONLY))
    commands = _command_ids(r, m["commands"], (*path, "commands"), version)
    by_name = {f.name: f for f in command}
    offsets: dict[str, tuple[int, int]] = {}  # byte offset and size of each command field in the row
    bit = 0
    for f in command:
        offsets[f.name] = (bit // 8, f.bits // 8)
        bit += f.bits
    modes = [
        _mode(r, item, (*path, "modes", i), commands, by_name, offsets)
        for i, item in enumerate(r.sequence(m["modes"], (*path, "modes")))
    ]
    names = [md.name for md in modes]
    if not names or len(set(names)) != len(names):
        raise r.err((*path, "modes"), "name the modes, each once")
    sm = r.mapping(m["states"], (*path, "states"), STATE_KEYS, required=STATE_KEYS)
    errors = []
    for i, item in enumerate(r.sequence(m["errors"], (*path, "errors"))):
        ep: PathT = (*path, "errors", i)
        em = r.mapping(item, ep, ("bit", "name"), required=("bit", "name"))
        errors.append(
            (r.integer(em["bit"], (*ep, "bit"), 1, 0xFFFFFFFF), r.string(em["name"], (*ep, "name")))
        )
    config = _endpoint_config(r, m, path, version)
    fields_named = _heartbeat_fields(r, m, path, by_name, {f.name for f in reply})
    request = by_name[fields_named["request_field"]]
    clear = bytes(
        r.integer(v, (*path, "clear", i), 0, 255)
        for i, v in enumerate(r.sequence(m.get("clear", []), (*path, "clear")))
    )
    return OdriveProtocol(
        protocol=version,
        commands=commands,
        modes=tuple(modes),
        mode=r.choice(m.get("mode", names[0]), (*path, "mode"), names),
        idle=r.integer(sm["idle"], (*path, "states", "idle"), 0, 255),
        closed_loop=r.integer(sm["closed_loop"], (*path, "states", "closed_loop"), 0, 255),
        errors=tuple(errors),
        watchdog_ms=r.number(m.get("watchdog_ms", 0.0), (*path, "watchdog_ms")),
        heartbeat_ms=r.number(m.get("heartbeat_ms", 100.0), (*path, "heartbeat_ms")),
        config=config,
        request_field=fields_named["request_field"],
        request_at=offsets[request.name],
        state_field=fields_named["state_field"],
        error_field=fields_named["error_field"],
        clear=clear,
    )


def _command_ids(r: Any, raw: Any, cp: PathT, version: str) -> dict[str, int]:
    """``commands:``: the CAN command id (0..0x1F) of each command of firmware ``version``, all distinct."""
    cm = r.mapping(raw, cp, (*COMMON, *ONLY["0.5"], *ONLY["0.6"]))
    other = next(v for v in ONLY if v != version)
    for name in ONLY[other]:
        if name in cm:
            raise r.err((*cp, name), f"{name} is a command of firmware {other}, not {version}", key=True)
    for name in (*COMMON, *ONLY[version]):
        if name not in cm:
            raise r.err(cp, f"firmware {version} has command '{name}': give its id")
    commands = {k: r.integer(v, (*cp, k), 0, 0x1F) for k, v in cm.items()}
    if len(set(commands.values())) != len(commands):
        raise r.err(cp, "two commands share an id")
    return commands


def _mode(
    r: Any,
    item: Any,
    mp: PathT,
    commands: dict[str, int],
    by_name: dict[str, Any],
    offsets: dict[str, tuple[int, int]],
) -> OdriveMode:
    """One entry of ``modes:``: its set-point command, control and input modes, and the fields it sends."""
    mm = r.mapping(item, mp, MODE_KEYS, required=MODE_KEYS)
    cmd = r.choice(mm["command"], (*mp, "command"), ("set_input_pos", "set_input_vel", "set_input_torque"))
    fields: list[SetpointField] = []
    size = 0
    for j, fraw in enumerate(r.sequence(mm["fields"], (*mp, "fields"))):
        fp: PathT = (*mp, "fields", j)
        fm = r.mapping(fraw, fp, SETPOINT_KEYS, required=("from", "type"))
        src = r.string(fm["from"], (*fp, "from"))
        if src not in by_name:
            raise r.err((*fp, "from"), f"'{src}' is not a command field ({', '.join(by_name)})")
        if by_name[src].scaled or by_name[src].bits % 8:
            raise r.err(
                (*fp, "from"), f"'{src}' is scaled or not whole bytes: a set-point takes a number as is"
            )
        kind = r.choice(fm["type"], (*fp, "type"), tuple(SETPOINT_TYPES))
        size += SETPOINT_TYPES[kind][1]
        at, nbytes = offsets[src]
        fields.append(
            SetpointField(
                src, kind, r.number(fm.get("scale", 1.0), (*fp, "scale")), at, by_name[src].type, nbytes
            )
        )
    if size > 8:
        raise r.err((*mp, "fields"), f"the fields take {size} bytes; a classic CAN frame has 8")
    return OdriveMode(
        r.name(mm["name"], (*mp, "name")),
        commands[cmd],
        r.integer(mm["control_mode"], (*mp, "control_mode"), 0, 0xFFFFFFFF),
        r.integer(mm["input_mode"], (*mp, "input_mode"), 0, 0xFFFFFFFF),
        tuple(fields),
    )


def _endpoint_config(r: Any, m: Mapping[Any, Any], path: PathT, version: str) -> tuple[ConfigItem, ...]:
    """``config:``: endpoint writes at bring-up (firmware 0.6 only: 0.5 has no endpoint access over CAN)."""
    config: list[ConfigItem] = []
    for i, item in enumerate(r.sequence(m.get("config", []), (*path, "config"))):
        gp: PathT = (*path, "config", i)
        if version != "0.6":
            raise r.err(gp, "firmware 0.5 has no endpoint access over CAN (RxSdo): configure it over USB")
        gm = r.mapping(item, gp, CONFIG_KEYS, required=CONFIG_KEYS)
        config.append(
            ConfigItem(
                r.string(gm["name"], (*gp, "name")),
                r.integer(gm["endpoint"], (*gp, "endpoint"), 0, 0xFFFF),
                r.choice(gm["type"], (*gp, "type"), tuple(CONFIG_TYPES)),
                r.number(gm["value"], (*gp, "value")),
            )
        )
    return tuple(config)


def _heartbeat_fields(
    r: Any, m: Mapping[Any, Any], path: PathT, by_name: dict[str, Any], replies: set[str]
) -> dict[str, str]:
    """The image fields of the requested state (a command field) and of the heartbeat's state and error."""
    fields_named: dict[str, str] = {}
    for key, default, pool in (
        ("request_field", "requested_state", by_name),
        ("state_field", "axis_state", replies),
        ("error_field", "axis_error", replies),
    ):
        name = r.string(m.get(key, default), (*path, key))
        if name not in pool:
            raise r.err((*path, key), f"'{name}' is not a {'command' if pool is by_name else 'reply'} field")
        fields_named[key] = name
    request = by_name[fields_named["request_field"]]
    if request.scaled or request.type != "uint" or request.bits % 8:
        raise r.err(
            (*path, "request_field"), f"'{request.name}' is not an unscaled uint field of whole bytes"
        )
    return fields_named


# -- codec -----------------------------------------------------------------------------------------------
def axis_state_frame(state: int) -> bytes:
    """Set_Axis_State data: the requested state, uint32, in an 8-byte frame (the DBC's length)."""
    return struct.pack("<I4x", state)


def controller_mode_frame(mode: OdriveMode) -> bytes:
    """Set_Controller_Mode data: control mode, input mode (uint32 each)."""
    return struct.pack("<II", mode.control_mode, mode.input_mode)


def heartbeat(data: bytes) -> tuple[int, int]:
    """``(axis error, axis state)`` of a heartbeat frame."""
    return struct.unpack_from("<I", data)[0], data[4]


def heartbeat_frame(error: int, state: int, procedure_result: int = 0, done: bool = True) -> bytes:
    """A heartbeat (firmware 0.6 layout: error, state, procedure result, trajectory done flag)."""
    return struct.pack("<IBBBx", error, state, procedure_result, 1 if done else 0)


def sdo_request(opcode: int, endpoint: int, value: bytes = bytes(4)) -> bytes:
    """RxSdo data: opcode (0 read, 1 write), uint16 endpoint id, reserved, 4 value bytes."""
    return struct.pack("<BHB", opcode, endpoint, 0) + value


def sdo_reply(data: bytes) -> tuple[int, bytes] | None:
    """``(endpoint, value bytes)`` of a TxSdo frame, None when it is not one."""
    if len(data) != 8:
        return None
    return struct.unpack_from("<H", data, 1)[0], bytes(data[4:8])


def pack_config(item: ConfigItem, value: float | None = None) -> bytes:
    v = item.value if value is None else value
    fmt = CONFIG_TYPES[item.type]
    return struct.pack(fmt, v if fmt == "<f" else int(v))


def unpack_config(item: ConfigItem, data: bytes) -> float:
    return float(struct.unpack(CONFIG_TYPES[item.type], data)[0])


def _source(f: SetpointField, row: Any) -> float:
    """Field ``f``'s value from an output row's wire bytes (``row``: any buffer, e.g. a numpy uint8 row)."""
    if f.source_type == "float32":
        return float(struct.unpack_from("<f", row, f.at)[0])
    return float(
        int.from_bytes(bytes(row[f.at : f.at + f.source_bytes]), "little", signed=f.source_type == "int")
    )


def encode_setpoint(mode: OdriveMode, row: Any, out: bytearray) -> None:
    """Mode ``mode``'s set-point frame data from an output row's wire bytes into ``out`` (8 bytes, zero
    padded); NaN in an int16 sends 0, out of range saturates (a float32 is sent as the image has it)."""
    at = 0
    out[:] = bytes(len(out))
    for f in mode.fields:
        x = _source(f, row) * f.scale
        fmt, size = SETPOINT_TYPES[f.type]
        if f.type == "int16":
            struct.pack_into(fmt, out, at, 0 if x != x else int(min(32767.0, max(-32768.0, round(x)))))
        else:
            struct.pack_into(fmt, out, at, x)
        at += size


def decode_setpoint(mode: OdriveMode, data: bytes) -> dict[str, float]:
    """The engineering values a set-point frame carries, keyed by their command field (``value = raw / scale``)."""
    out: dict[str, float] = {}
    at = 0
    for f in mode.fields:
        fmt, size = SETPOINT_TYPES[f.type]
        out[f.source] = float(struct.unpack_from(fmt, data, at)[0]) / f.scale
        at += size
    return out


def requested_state(proto: OdriveProtocol, row: Any) -> int:
    """The axis state the image asks for (its request field, from an output row's wire bytes; 0: none)."""
    at, size = proto.request_at
    return int.from_bytes(bytes(row[at : at + size]), "little")
