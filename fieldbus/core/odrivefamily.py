"""The ODrive family (``rawcan: family: odrive``, CANSimple) on the family protocol (:mod:`fieldbus.core.canfamily`).

Codec and map section: :mod:`fieldbus.core.odrive` (ids ``node << 5 | command``, little-endian).

- A cycle: Set_Axis_State when the image's requested state changed (sent once), the mode's set-point
  (Set_Input_Pos / Vel / Torque, from the output row) unless the image asks IDLE (the safe stop writes
  IDLE: the axis lets go), and a remote frame asking Get_Encoder_Estimates, whose 8-byte answer is the
  motor's cycle reply (the first 8 bytes of its input row).
- Heartbeats, whenever they come (:meth:`OdriveFamily.take`): axis error and state into the input row;
  the error is the motor's fault code, named by its bits. On firmware 0.6 a new error asks Get_Error with
  the next cycle; its answer (active errors, disarm reason) is kept in :attr:`OdriveFamily.active_errors`.
- Bring-up, each wait bounded: ``configure`` asks a heartbeat (RTR) and awaits it, sends
  Set_Controller_Mode and writes the map's endpoints (RxSdo), each read back (TxSdo); ``enter`` writes
  CLOSED_LOOP_CONTROL into the image's requested state, sends it and awaits a heartbeat saying so;
  ``exit`` sends IDLE; ``clear`` Clear_Errors. Recovery: Clear_Errors, then closed loop, awaited.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from fieldbus.core.canfamily import (
    CanFamily,
    ClassicSection,
    FamilyMotor,
    Frame,
    FrameTime,
    Remote,
    Request,
    StepRefused,
    Steps,
)
from fieldbus.core.odrive import (
    SDO_READ,
    SDO_WRITE,
    OdriveMode,
    OdriveProtocol,
    axis_state_frame,
    controller_mode_frame,
    encode_setpoint,
    heartbeat,
    pack_config,
    parse_odrive,
    requested_state,
    sdo_reply,
    sdo_request,
    unpack_config,
)
from fieldbus.core.yamlsrc import PathT

HEARTBEAT_WAIT_S = 2.0  # the least wait for a heartbeat (three heartbeat periods when that is longer)
SDO_WAIT_S = 0.2  # the wait for a TxSdo answer
COMMAND_BYTES = 8  # a set-point frame, zero-padded (Set_Input_Torque carries 4 bytes of numbers)
REPLY_BYTES = 8  # Get_Encoder_Estimates (2 x float32) and the heartbeat (the DBC's length)


@dataclass
class OdFrame:
    """A frame of the cycle (``remote``: an RTR asking ``len(data)`` bytes)."""

    can_id: int
    extended: bool
    data: bytearray
    remote: bool = False


@dataclass
class _Axis:
    motor: FamilyMotor
    proto: OdriveProtocol
    mode: OdriveMode
    setpoints: dict[int, OdFrame]  # by set-point command id
    state: OdFrame  # Set_Axis_State
    estimates: OdFrame  # the Get_Encoder_Estimates RTR
    get_error: OdFrame | None  # firmware 0.6: the Get_Error RTR
    error_at: int  # the input row's byte offsets of the axis error (uint32) and state (uint8)
    state_at: int
    sent_state: int = 0  # the last Set_Axis_State sent (0: none)
    heartbeat: tuple[int, int] | None = None  # (axis error, axis state) of the last heartbeat


class OdriveFamily(CanFamily):
    """The ODrive axes of one bus; a motor's ``config`` is its :class:`~fieldbus.core.rawcan.RawCanConfig`
    (``config.odrive``: the CANSimple section)."""

    name = "odrive"
    emulator = "sim_slaves.odrive:OdriveSimulator"
    section = "odrive"
    max_bits = 128  # the image is no one frame: set-points built per mode, the reply plus the heartbeat

    @classmethod
    def parse_section(cls, r: Any, classic: ClassicSection) -> Any:
        """``rawcan.odrive``: CANSimple commands, modes, states, errors (:func:`fieldbus.core.odrive.parse_odrive`)."""
        if "odrive" not in classic.mapping or classic.byte_order != "little":
            raise r.err(
                classic.path, "family odrive needs byte_order: little and its 'odrive' section (CANSimple)"
            )
        path = (*classic.path, "odrive")
        return parse_odrive(r, classic.mapping["odrive"], path, classic.command, classic.reply)

    def __init__(self, motors: Sequence[FamilyMotor]) -> None:
        super().__init__(motors)
        self._axes: dict[int, _Axis] = {}
        self._replies: dict[int, int] = {}  # Get_Encoder_Estimates id -> motor index
        self._side: dict[int, tuple[int, str]] = {}  # heartbeat / get_error / txsdo id -> (motor, kind)
        self._out: list[OdFrame] = []  # the cycle's frames (one list, refilled)
        self._pending: list[OdFrame] = []  # requests that go out with the next cycle
        #: Firmware 0.6 Get_Error answers by motor index: (active errors, disarm reason).
        self.active_errors: dict[int, tuple[int, int]] = {}
        for m in motors:
            proto: OdriveProtocol = m.config.odrive
            if not 0 <= m.node < 0x40:
                raise ValueError(
                    f"an ODrive node id is 0..63 (11-bit id = node << 5 | command), not {m.node}"
                )
            offsets, at = {}, 0
            for f in m.config.reply:
                offsets[f.name] = at
                at += f.bits // 8
            estimates = proto.can_id(m.node, "get_encoder_estimates")
            if estimates in self._replies:
                raise ValueError(f"two ODrive axes have node id {m.node}")
            ax = _Axis(
                m,
                proto,
                proto.mode_named(proto.mode),
                {md.command: OdFrame(m.node << 5 | md.command, False, bytearray(8)) for md in proto.modes},
                OdFrame(proto.can_id(m.node, "set_axis_state"), False, bytearray(8)),
                OdFrame(estimates, False, bytearray(REPLY_BYTES), remote=True),
                OdFrame(proto.can_id(m.node, "get_error"), False, bytearray(8), remote=True)
                if proto.protocol == "0.6"
                else None,
                offsets[proto.error_field],
                offsets[proto.state_field],
            )
            self._axes[m.index] = ax
            self._replies[estimates] = m.index
            self._side[proto.can_id(m.node, "heartbeat")] = (m.index, "heartbeat")
            if proto.protocol == "0.6":
                self._side[proto.can_id(m.node, "get_error")] = (m.index, "get_error")

    @classmethod
    def parse(cls, r: Any, raw: Any, path: PathT) -> tuple[Any, tuple[Any, ...], tuple[Any, ...]]:
        from fieldbus.core.rawcan import parse_classic

        return parse_classic(r, raw)

    @classmethod
    def max_motors(cls, config: Any) -> int | None:
        """Node ids 1..63 (6 bits of the 11-bit id)."""
        return 63

    @classmethod
    def wire_frames(cls, name: str, config: Any, node: int) -> list[FrameTime]:
        """The mode's set-point (8 bytes), the Get_Encoder_Estimates remote frame and its 8-byte answer;
        the heartbeat (8 bytes every ``heartbeat_ms``) as a background frame."""
        od: OdriveProtocol = config.odrive
        mode = od.mode_named(od.mode)
        estimates = od.can_id(node, "get_encoder_estimates")
        rtr = FrameTime(estimates, 0, f"{name} encoder RTR", remote=True)
        out = [
            FrameTime(node << 5 | mode.command, COMMAND_BYTES, f"{name} {mode.name} set-point"),
            rtr,
            FrameTime(estimates, REPLY_BYTES, f"{name} encoder estimates", after=rtr.label),
        ]
        if od.heartbeat_ms > 0:
            hb = od.can_id(node, "heartbeat")
            out.append(FrameTime(hb, REPLY_BYTES, f"{name} heartbeat", period_us=od.heartbeat_ms * 1000.0))
        return out

    # -- the cycle ------------------------------------------------------------------------------------
    def cycle(self) -> list[OdFrame]:
        out = self._out
        out.clear()
        if self._pending:
            out.extend(self._pending)
            self._pending.clear()
        for ax in self._axes.values():
            row = ax.motor.outputs  # the wire bytes (byte_order little: in frame order)
            want = requested_state(ax.proto, row)
            if want and want != ax.sent_state:
                struct.pack_into("<I", ax.state.data, 0, want)
                ax.sent_state = want
                out.append(ax.state)
            if want != ax.proto.idle:
                frame = ax.setpoints[ax.mode.command]
                encode_setpoint(ax.mode, row, frame.data)
                out.append(frame)
            out.append(ax.estimates)
        return out

    def carries(self, can_id: int, extended: bool, data: bytes) -> list[int]:
        i = self._replies.get(can_id)
        if extended or i is None or len(data) != REPLY_BYTES:
            return []
        return [i]

    def route(self, can_id: int, extended: bool, data: bytes) -> list[int]:
        motors = self.carries(can_id, extended, data)
        for i in motors:
            self._axes[i].motor.inputs[:REPLY_BYTES] = np.frombuffer(data, dtype=np.uint8)
        return motors

    def take(self, can_id: int, extended: bool, data: bytes) -> tuple[int, ...]:
        """A heartbeat (axis error and state into the input row) or a Get_Error answer."""
        got = None if extended else self._side.get(can_id)
        if got is None:
            return ()
        i, kind = got
        ax = self._axes[i]
        if kind == "heartbeat" and len(data) >= 5:
            error, state = heartbeat(data)
            row = ax.motor.inputs
            row[ax.error_at : ax.error_at + 4] = np.frombuffer(data[:4], dtype=np.uint8)
            row[ax.state_at] = state
            last, ax.heartbeat = ax.heartbeat, (error, state)
            new = error and (last is None or last[0] != error)
            if new and ax.get_error is not None and ax.get_error not in self._pending:
                self._pending.append(ax.get_error)  # the detail: active errors and the disarm reason
            return (i,)
        if kind == "get_error" and len(data) == 8:
            self.active_errors[i] = (int.from_bytes(data[:4], "little"), int.from_bytes(data[4:], "little"))
        return ()

    def error(self, motor: int) -> tuple[int, str | None]:
        """The axis error bits of the last heartbeat and their names (None: no error)."""
        ax = self._axes[motor]
        code = int.from_bytes(bytes(ax.motor.inputs[ax.error_at : ax.error_at + 4]), "little")
        return code, ax.proto.error_names(code) if code else None

    # -- special frames -------------------------------------------------------------------------------
    def _frame(self, ax: _Axis, command: str, data: bytes) -> Frame:
        return ax.proto.can_id(ax.motor.node, command), False, data

    def _state(self, ax: _Axis, state: int) -> Frame:
        """Set_Axis_State ``state`` (remembered as sent: the cycle sends it again only when the image asks
        another)."""
        ax.sent_state = state
        return self._frame(ax, "set_axis_state", axis_state_frame(state))

    def commands(self, which: str, motor: int | None = None) -> list[Frame]:
        """``clear``: Clear_Errors; ``enable`` / ``disable``: Set_Axis_State closed loop / IDLE."""
        out = []
        for i, ax in self._axes.items():
            if motor is not None and i != motor:
                continue
            if which == "clear":
                out.append(self._frame(ax, "clear_errors", ax.proto.clear))
            elif which in ("enable", "disable"):
                out.append(self._state(ax, ax.proto.closed_loop if which == "enable" else ax.proto.idle))
        return out

    def stop_frames(self) -> list[Frame]:
        """Set_Axis_State IDLE to every axis (the controller lets go)."""
        return self.commands("disable")

    # -- bring-up, modes, endpoints -------------------------------------------------------------------
    def _heartbeat(self, i: int, state: int | None = None) -> Request:
        """Ask motor ``i`` for a heartbeat (RTR: one sent before the bus listened is not repeated by a
        controller whose timer is slow) and await one, in ``state`` when given."""
        ax = self._axes[i]
        ax.heartbeat = None  # the one read comes after this request

        def reached() -> bool:
            seen = ax.heartbeat
            return seen is not None and (state is None or seen[1] == state)

        return Request(
            self._frame(ax, "heartbeat", Remote(bytes(REPLY_BYTES))),
            (i,),
            until=reached,
            timeout_s=max(HEARTBEAT_WAIT_S, 3 * ax.proto.heartbeat_ms / 1000),
            what="a heartbeat" + (f" with axis state {state}" if state is not None else ""),
        )

    def _closed_loop(self, i: int) -> Iterator[Request]:
        """CLOSED_LOOP_CONTROL written into the image's requested state, sent, awaited in a heartbeat."""
        ax = self._axes[i]
        at, size = ax.proto.request_at
        ax.motor.outputs[at : at + size] = np.frombuffer(
            ax.proto.closed_loop.to_bytes(size, "little"), dtype=np.uint8
        )
        wait = self._heartbeat(i, ax.proto.closed_loop)
        yield Request(self._state(ax, ax.proto.closed_loop))
        yield wait

    def configure(self) -> Steps:
        """Each axis: a heartbeat seen; Set_Controller_Mode of the map's mode; its endpoints written, read back."""
        for i in self._axes:
            yield from self._configure(i)

    def bring_up(self, which: str) -> Iterator[Request]:
        if which == "enter":
            for i in self._axes:
                yield from self._closed_loop(i)
        elif which in ("exit", "clear"):
            yield from (
                Request(f) for f in (self.stop_frames() if which == "exit" else self.commands("clear"))
            )

    def _configure(self, i: int) -> Steps:
        """A heartbeat seen; Set_Controller_Mode of the map's mode; the map's endpoints written, read back."""
        ax = self._axes[i]
        yield self._heartbeat(i)
        yield Request(self._frame(ax, "set_controller_mode", controller_mode_frame(ax.mode)))
        for item in ax.proto.config:
            want = pack_config(item)
            back = unpack_config(item, (yield from self.access(i, item.endpoint, want)))
            if back != unpack_config(item, want):
                raise StepRefused(
                    i,
                    f"endpoint {item.name} ({item.endpoint}) reads back {back:g} after writing {item.value:g}",
                )

    def recover(self, motor: int) -> Iterator[Request]:
        """Clear_Errors, then CLOSED_LOOP_CONTROL, awaited in a heartbeat."""
        yield from (Request(f) for f in self.commands("clear", motor))
        yield from self._closed_loop(motor)

    def set_mode(self, motor: int, mode: str) -> Steps:
        """Set_Controller_Mode (CANSimple reads it back on no firmware); set-points in ``mode`` after."""
        ax = self._axes[motor]
        try:
            new = ax.proto.mode_named(mode)
        except KeyError:
            raise ValueError(
                f"no mode '{mode}' (have: {', '.join(m.name for m in ax.proto.modes)})"
            ) from None
        yield Request(self._frame(ax, "set_controller_mode", controller_mode_frame(new)))
        ax.mode = new

    def mode(self, motor: int) -> str | None:
        return self._axes[motor].mode.name

    @classmethod
    def register_key(
        cls, config: Any, reg: str, type_name: str | None, writing: bool
    ) -> tuple[int, str, str, bool]:
        """An endpoint by its name in the map's ``odrive.config`` (its type) or its id (0..65535; a write
        needs ``type_name``); firmware 0.6 only."""
        od: OdriveProtocol = config.odrive
        if od.protocol != "0.6":
            raise ValueError(
                f"ODrive firmware {od.protocol} has no endpoint access over CAN (RxSdo is firmware 0.6): "
                "configure it over USB (odrivetool)"
            )
        item = next((c for c in od.config if c.name == reg), None)
        if item is not None:
            return item.endpoint, item.name, type_name or item.type, False
        try:
            endpoint = int(reg, 0)
        except ValueError:
            named = ", ".join(c.name for c in od.config) or "none"
            raise ValueError(
                f"'{reg}' is neither an endpoint id (0..65535) nor an endpoint of the map's odrive.config "
                f"(named there: {named})"
            ) from None
        if not 0 <= endpoint <= 0xFFFF:
            raise ValueError(f"endpoint ids are 0..65535, not {endpoint}")
        if type_name is None and writing:
            raise ValueError(f"endpoint {endpoint}: give --type float32, uint32, int32 or bool")
        return endpoint, f"endpoint {endpoint}", type_name or "uint32", False

    def access(self, motor: int, key: int, value: bytes | None = None) -> Steps:
        """Endpoint ``key`` through RxSdo (firmware 0.6): written when ``value`` is given, then read; the 4
        value bytes of the TxSdo answer."""
        ax = self._axes[motor]
        if ax.proto.protocol != "0.6":
            raise ValueError("no endpoint access over CAN (ODrive firmware 0.6 only)")
        if value is not None:
            yield Request(self._frame(ax, "rxsdo", sdo_request(SDO_WRITE, key, value)))
        txsdo = ax.proto.can_id(ax.motor.node, "txsdo")

        def answers(can_id: int, extended: bool, data: bytes) -> bool:
            got = sdo_reply(data) if can_id == txsdo and not extended else None
            return got is not None and got[0] == key

        data = yield Request(
            self._frame(ax, "rxsdo", sdo_request(SDO_READ, key)),
            (motor,),
            answer=answers,
            timeout_s=SDO_WAIT_S,
            what=f"the read of endpoint {key}",
        )
        got = sdo_reply(data or b"")
        if got is None:  # not resumed without an answer: the transport names the time-out
            raise StepRefused(motor, f"endpoint {key}: no TxSdo answer")
        return got[1]
