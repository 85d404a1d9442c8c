"""Raw-CAN backend for MIT-mode actuators on python-can.

One command frame per motor per cycle (CAN id ``command_id + node_id``), one
reply expected from each; replies are routed by the map's ``node_field`` (the
motor-id byte) or by CAN id. Frames are the byte-reversed wire rows of the
process image (see :mod:`fieldbus.core.rawcan`). ``op()`` sends the
enter-motor-mode frame to every motor and waits for each to answer;
``stop()`` sends exit-motor-mode.

``receive()`` returns the number of replies that arrived (the "working
counter" of a CAN cycle) and ``arrived()`` says which motors answered. A
reply that comes after its cycle's timeout is dropped at the next ``send()``
and counted in ``late_frames``: it never passes for the next cycle's; a second
reply of a motor in one cycle is counted in ``extra_frames``. Driver errors
raise :class:`~fieldbus.errors.BusIoError` and are counted with error frames
and bus-off (:class:`~fieldbus.backends.canfaults.CanFaults`); ``stop()`` and
``close()`` never raise. ``open()`` takes the CAN channel's lock
(:mod:`fieldbus.backends.buslock`): one master per channel.

A family's error code is watched (a rising code outside its ``ok_codes`` is one counted, named fault in
:attr:`RawCanBackend.motor_faults` / :attr:`RawCanBackend.faults`). A fault's onset is also queued for :meth:`RawCanBackend.take_motor_events`, which the
network calls every cycle: a :class:`MotorFaultEvent` (a :class:`~fieldbus.core.drivefault.DriveFault`
with the family's name) in ``CycleResult.events`` and recordings, once per onset.

Family ``odrive`` (:mod:`fieldbus.core.odrive`, CANSimple): each cycle a motor gets its mode's
set-point frame (``node << 5 | 0x0C/0x0D/0x0E``) and a remote frame asking for Get_Encoder_Estimates,
whose answer is the cycle's reply; heartbeats (and, firmware 0.6, Get_Error answers) update the
image's ``axis_error`` / ``axis_state`` whenever they come, a new error is a counted fault named by
its bits; the image's ``requested_state`` is sent as Set_Axis_State when it changes, and while it is
IDLE no set-point goes out (the safe stop writes IDLE); ``op()`` requests CLOSED_LOOP_CONTROL and waits
for the heartbeats to say so; ``stop()`` requests IDLE. ``configure()`` waits for a heartbeat, sends
Set_Controller_Mode and writes the map's endpoints (RxSdo, 0.6) and reads them back (TxSdo).

Families on the protocol (:mod:`fieldbus.core.canfamily`, registered in :func:`~fieldbus.core.canfamily.families`,
a third party's through the ``fieldbus.rawcan_families`` entry points) are reached through it only: their
cycle frames, reply routing, special and stop frames, recovery requests and error codes, and its
transactions (:data:`~fieldbus.core.canfamily.Steps`: ``configure()``, :meth:`RawCanBackend.set_mode`,
:meth:`RawCanBackend.register`), each request's answer awaited here. Family ``frames``
(:mod:`fieldbus.core.canframes`) is one: a protocol described in data; its command frames (per motor, or
shared by several motors of the bus) are filled from the image's output rows and its feedback frames
routed into the motors' input rows; enable / disable / zero are the map's byte patterns (no answer
awaited), and ``stop()`` sends every motor's ``safe_value`` command before the disable pattern.

CAN FD: a bus with a ``data_bitrate`` (or ``can_options: {fd: true}``) sends every data frame as CAN FD,
with bit-rate switching when the data rate differs from the nominal one (remote frames stay classic).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from fieldbus.backends.base import Backend
from fieldbus.backends.buslock import InterfaceLock, lock_can_bus
from fieldbus.backends.canbus import attach_can_bus, release_can_bus
from fieldbus.backends.canfaults import CanFaults
from fieldbus.core import odrive
from fieldbus.core.canfamily import CanFamily, FamilyMotor, Request, Steps, families
from fieldbus.core.drivefault import DriveFault
from fieldbus.core.network import Bus
from fieldbus.errors import BackendUnavailableError, BusTimeoutError, FieldbusError, StateTransitionError
from fieldbus.runtime.clock import monotonic_s
from fieldbus.wire.canlog import open_log

try:
    import can
except ImportError as exc:  # pragma: no cover - depends on the install
    raise BackendUnavailableError(
        f"the rawcan backend needs python-can ({exc}): pip install 'fieldbus[can]'"
    ) from None

ENTER_TIMEOUT_S = 2.0  # bring-up (outside the cycle): generous, a loaded host schedules the motors late
REGISTER_TIMEOUT_S = 0.2  # a register read/write answer, bring-up and mode switches only
FAULT_LOG = 100  # motor faults kept per backend (oldest dropped; motor_faults counts them all)


@dataclass(frozen=True)
class MotorFault:
    """A motor reported an error code outside the family's ``ok_codes``: which, when (cycle count) and its name."""

    cycle: int
    slave: str
    code: int
    name: str

    def __str__(self) -> str:
        return f"{self.slave}: motor error 0x{self.code:X} {self.name}"


@dataclass(frozen=True)
class MotorFaultEvent(DriveFault):
    """A raw-CAN motor fault as a cycle event (``CycleResult.events``, recordings): the onset of a family's
    error code outside its ``ok_codes`` or of a new ODrive axis error, with the family's name for it.

    ``code`` is the family's own code (an error nibble, ODrive axis error bits), not a CiA 402 0x603F.
    """

    reason: str = ""  # the family's name of ``code`` ("overload", "MOTOR_OVER_TEMP, ...")

    @property
    def name(self) -> str:
        return self.reason

    def __str__(self) -> str:
        return f"{self.slave} ({self.group}[{self.axis}]): motor fault 0x{self.code or 0:X} {self.reason}"


_NO_EVENTS: tuple[MotorFaultEvent, ...] = ()


class RawCanBackend(CanFaults, Backend):
    """MIT-mode motors on one CAN bus (``interface`` = python-can channel)."""

    kind = "rawcan"
    pdo_align = 8

    def __init__(self, bus: Bus, **options: Any) -> None:
        super().__init__(bus, **options)
        self._bus: Any = options.get("can_bus")  # tests may hand in a bus instance
        fd_option = dict(bus.can_options).get("fd") is True
        self._fd = bus.data_bitrate is not None or fd_option  # CAN FD data frames
        self._brs = bus.data_bitrate is not None and bus.data_bitrate != bus.bitrate  # bit-rate switch
        self._in_rows = [self.in_row(i) for i in range(self.n_slaves)]
        self._own_bus = self._bus is None
        self._cmd: list[tuple[Any, npt.NDArray[np.uint8], npt.NDArray[np.uint8]]] = []
        self._route: dict[tuple[int, int], int] = {}  # (can id, node byte or -1) -> slave index
        self._node_byte: dict[int, int] = {}  # reply CAN id -> index of the node byte in the frame, or -1
        self._arrived = np.zeros(self.n_slaves, dtype=bool)
        # each motor's reply bytes as the frame has them: its input row, reversed (a view)
        self._reply_rows = [
            self.in_row(i) if self._little(i) else self.in_row(i)[::-1] for i in range(self.n_slaves)
        ]
        self._reply_len = [8 if self._od_of(i) else row.size for i, row in enumerate(self._reply_rows)]
        self._timeout_s = bus.receive_timeout_us / 1e6
        self._lock: InterfaceLock | None = None
        self._now = monotonic_s(
            options.get("clock")
        )  # seconds; in tests a virtual clock's (fieldbus.testing)
        self._codes = np.zeros(self.n_slaves, dtype=np.int64)  # last error code per motor
        self.motor_faults = 0  # faults reported since open, ever (the kept list is bounded)
        self.faults: deque[MotorFault] = deque(maxlen=FAULT_LOG)  # newest last
        self._onsets: deque[tuple[int, int, str]] = deque(
            maxlen=FAULT_LOG
        )  # (motor, code, name) not yet taken
        self._cycles = 0
        # family odrive: protocol, mode, set-point frames by command id, the RTR, heartbeat routing
        self._od: list[odrive.OdriveProtocol | None] = [self._od_of(i) for i in range(self.n_slaves)]
        self._od_mode: list[odrive.OdriveMode | None] = [None] * self.n_slaves
        self._od_msgs: list[dict[int, Any]] = [{} for _ in range(self.n_slaves)]
        self._od_rtr: list[Any] = [None] * self.n_slaves
        self._od_sent_state = [0] * self.n_slaves  # the last Set_Axis_State sent (0: none)
        self._od_side: dict[
            int, tuple[int, str]
        ] = {}  # CAN id -> (motor, "heartbeat" | "get_error" | "txsdo")
        self._od_at: list[tuple[int, int]] = [
            (0, 0)
        ] * self.n_slaves  # image offsets of axis error, axis state
        self._od_hb: list[tuple[int, int] | None] = [None] * self.n_slaves  # last heartbeat (error, state)
        self.active_errors: dict[
            str, tuple[int, int]
        ] = {}  # 0.6 Get_Error answers: (active errors, disarm reason)
        self._sdo_answer: tuple[int, int, bytes] | None = None  # (motor, endpoint, value) of the last TxSdo
        declared: dict[str, list[FamilyMotor]] = {}  # families on the protocol: their motors
        self._fr = [False] * self.n_slaves  # motor i runs on a CanFamily
        for i, area in enumerate(self.areas):
            cfg = area.slave.map.rawcan
            if cfg is None:
                raise FieldbusError(
                    f"bus '{bus.name}': slave {area.slave.name} map {area.slave.map.name} has no rawcan section"
                )
            node = area.slave.node_id or 0
            out_row = self.out_row(i)
            msg = self._message(
                arbitration_id=cfg.command_id + node, data=bytearray(out_row.size), is_extended_id=False
            )
            # the frame's data bytearray seen as a numpy array: encoding writes straight into it
            self._cmd.append((msg, out_row[::-1], np.frombuffer(msg.data, dtype=np.uint8)))
            if cfg.protocol is not None:
                self._fr[i] = True
                motor = FamilyMotor(i, node, cfg.protocol, out_row, self._in_rows[i], area.slave.name)
                declared.setdefault(cfg.family, []).append(motor)
                continue
            reply_id = cfg.reply_can_id(node)
            if cfg.odrive is not None:
                reply_id = self._odrive_init(i, cfg, node)
            byte = -1
            if cfg.node_field:
                bit = 0
                for f in cfg.reply:
                    if f.name == cfg.node_field:
                        break
                    bit += f.bits
                if bit % 8 or next(f.bits for f in cfg.reply if f.name == cfg.node_field) != 8:
                    raise FieldbusError(
                        f"{area.slave.map.name}: node_field must be a whole byte of the reply"
                    )
                byte = bit // 8
            self._node_byte[reply_id] = byte
            key = (reply_id, node if byte >= 0 else -1)
            if key in self._route:
                raise FieldbusError(
                    f"bus '{bus.name}': two motors answer as CAN id 0x{reply_id:X} node {node}"
                )
            self._route[key] = i
        registered = families() if declared else {}
        try:
            self._fams: list[CanFamily] = [registered[name](ms) for name, ms in declared.items()]
        except ValueError as exc:
            raise FieldbusError(f"bus '{bus.name}': {exc}") from None
        self._fam_of: dict[int, CanFamily] = {i: f for f in self._fams for i in f.motors}
        # each family's cycle frames, a message built once around each (their data rewritten in place),
        # by the frame's id(): a family with modes sends another frame object after a switch
        self._fam_msgs: list[tuple[CanFamily, dict[int, Any]]] = [(f, {}) for f in self._fams]
        self._families = bool(self._fam_of)
        self._odrives = any(p is not None for p in self._od)
        # last: a refused configuration above leaves no file open
        self._log = open_log(options.get("can_log"))  # every frame to a python-can log file

    @property
    def expected_wkc(self) -> int:
        """One reply per motor per cycle."""
        return self.n_slaves

    @property
    def late_replies(self) -> int:
        """Older name of :attr:`late_frames`."""
        return self.late_frames

    def open(self) -> None:
        """Lock the channel (:class:`~fieldbus.errors.InterfaceInUseError` when another master has it), open it."""
        if self._lock is None:
            self._lock = lock_can_bus(self.bus)
        self._bus = attach_can_bus(self.bus, self._bus, self._log)

    def _message(self, **kw: Any) -> Any:
        """A python-can frame; on a CAN FD bus a data frame is FD (bit-rate switched when the rates differ)."""
        if self._fd and not kw.get("is_remote_frame"):
            kw.update(is_fd=True, bitrate_switch=self._brs)
        return can.Message(**kw)

    def register(
        self, slave: int | str, register: int, value: float | None = None, *, is_float: bool = False
    ) -> float:
        """Read (``value`` None) or write-and-confirm a register of a motor whose family has registers
        (its family's :attr:`~fieldbus.core.canfamily.CanFamily.register_table`); the value answered.

        Blocking (outside the cycle, or between cycles). Raises :class:`~fieldbus.errors.BusTimeoutError`
        when the motor does not answer, :class:`~fieldbus.errors.BusIoError` when the driver fails.
        """
        i = slave if isinstance(slave, int) else self.slave_index(slave)
        got: float = self._transact(self._registers_of(i).register(i, register, value, is_float))
        return got

    def save_registers(self, slave: int | str) -> None:
        """Store a motor's registers to its flash (a family's transaction: a motor may answer only while disabled).

        Blocking, outside the cycle. Raises :class:`~fieldbus.errors.BusTimeoutError` without an answer.
        """
        i = slave if isinstance(slave, int) else self.slave_index(slave)
        self._transact(self._registers_of(i).save(i))

    def _registers_of(self, i: int) -> CanFamily:
        fam = self._fam_of.get(i)
        if fam is None or fam.register_table is None:
            raise FieldbusError(f"{self.areas[i].slave.name}: its map's family has no registers over CAN")
        return fam

    def _transact(self, steps: Steps) -> Any:
        """Run a family's transaction: each request sent, its answer (or None after its time-out) sent back
        in; its result. A refusal or time-out of the family names this bus."""
        answer: bytes | None = None
        try:
            while True:
                try:
                    req = steps.send(answer)
                except StopIteration as done:
                    return done.value
                answer = self._ask(req)
        except StateTransitionError as exc:
            raise StateTransitionError(f"bus '{self.bus.name}': {exc}", slave=exc.slave) from None
        except BusTimeoutError as exc:
            raise BusTimeoutError(f"bus '{self.bus.name}': {exc}") from None

    def _ask(self, req: Request) -> bytes | None:
        """Send a transaction's request; the data of the frame that answers it, or None (none in time)."""
        self._drain()
        self._send_raw(*req.frame)
        if req.answer is None:
            return None
        deadline = self._now() + req.timeout_s
        try:
            while (left := deadline - self._now()) > 0:
                msg = self._bus.recv(timeout=left)
                if msg is None or msg.is_error_frame or msg.is_remote_frame:
                    continue
                data = bytes(msg.data)
                if req.answer(msg.arbitration_id, msg.is_extended_id, data):
                    return data
        except (can.CanError, OSError) as exc:
            raise self._io_failed("register access", exc) from exc
        return None

    def set_mode(self, slave: int | str, mode: str) -> None:
        """Switch a motor to ``mode`` (a mode name of its map) by its family's transaction (a mode register
        written and read back), then its commands go out as that mode's frames, its own channels
        (``<mode>.<field>``) first seeded where the motor is (position as read, speed and torque limits 0):
        a switch starts no motion by itself, a value left there from an earlier use of the mode is never
        sent. Blocking: call it between cycles.
        An ODrive gets Set_Controller_Mode (CANSimple has no read-back of it; firmware 0.6 could read the
        endpoint) and its set-points go out as that mode's command from the next cycle."""
        i = slave if isinstance(slave, int) else self.slave_index(slave)
        fam = self._fam_of.get(i)
        if fam is not None:  # its family's transaction; the mode's own channels start where the motor is
            self._transact(fam.set_mode(i, mode))
            self._seed_from_actual(i, within=f"{mode}.")
            return
        od = self._od[i]
        if od is not None:
            try:
                new_od = od.mode_named(mode)
            except KeyError:
                raise FieldbusError(
                    f"{self.areas[i].slave.name}: no mode '{mode}' (have: {', '.join(m.name for m in od.modes)})"
                ) from None
            try:
                self._od_frame(i, "set_controller_mode", odrive.controller_mode_frame(new_od))
            except (can.CanError, OSError) as exc:
                raise self._io_failed("send", exc) from exc
            self._od_mode[i] = new_od
            return
        raise FieldbusError(f"{self.areas[i].slave.name}: its map's family has no modes")

    def mode(self, slave: int | str) -> str | None:
        """The mode a motor's commands are sent in (None: its family has no modes)."""
        i = slave if isinstance(slave, int) else self.slave_index(slave)
        if (fam := self._fam_of.get(i)) is not None:
            return fam.mode(i)
        m = self._od_mode[i]
        return m.name if m is not None else None

    def error_code(self, slave: int | str) -> int:
        """The error code of the motor's last accepted reply (families with error codes)."""
        return int(self._codes[slave if isinstance(slave, int) else self.slave_index(slave)])

    def clear_errors(self) -> list[str]:
        """Send the clear-error frame to every motor that has one; returns the motors that did not answer. The
        motors stay disabled: :meth:`recover` clears one motor's fault and enables it again."""
        return [self.areas[i].slave.name for i in self._special("clear")]

    def recover(self, slave: int | str) -> bool:
        """Clear motor ``slave``'s fault and enable it again by its family's own sequence, between cycles
        (each answer awaited at most ``ENTER_TIMEOUT_S``); True when it is enabled again.

        First its set-points are seeded from where it is (position as read; velocity, torque and currents 0;
        the controller's gains kept: an MIT motor holds where it is), so enabling starts no motion by
        itself: the controller writes its targets after.
        A family on the protocol: its recovery requests (MIT: enter motor mode, answered; declarative,
        ``frames``: the map's clear and enable patterns, if any), then its
        :meth:`~fieldbus.core.canfamily.CanFamily.enabled`; ODrive: Clear_Errors, then CLOSED_LOOP_CONTROL,
        awaited in the heartbeat. Raises :class:`~fieldbus.errors.BusIoError` when the driver fails.
        """
        i = slave if isinstance(slave, int) else self.slave_index(slave)
        self._seed_from_actual(i)
        cfg = self.areas[i].slave.map.rawcan
        assert cfg is not None
        proto = self._od[i]
        if proto is not None:
            a = self.areas[i]
            self.groups[a.group].image.outputs.values[a.row][proto.request_field] = proto.closed_loop
            try:
                self._od_frame(i, "clear_errors", proto.clear)
                self._od_hb[i] = None
                self._od_request_state(i, proto.closed_loop)
                self._od_wait_heartbeat(i, proto.closed_loop)
            except StateTransitionError:
                return False
            except (can.CanError, OSError) as exc:
                raise self._io_failed("send", exc) from exc
            self._codes[i] = 0
            return True
        fam = self._fam_of.get(i)
        if fam is not None:  # the family's recovery requests (declarative: the map's clear, enable)
            if self._requests(fam.recover(i)) or not fam.enabled(i):
                return False
            self._codes[i] = err[0] if (err := fam.error(i)) is not None else 0
            return True
        return self._answered(i, cfg.enter)

    def clear_fault(self, slave: int | str) -> bool:
        """Clear motor ``slave``'s fault by its family's clear command and leave it disabled (outside a
        session: ``fieldbus register --clear-fault``; in one, :meth:`recover` also enables it). A family
        on the protocol: its clear requests, True when each awaited reply came (its code then in :meth:`error_code`);
        ODrive: Clear_Errors (the heartbeat tells); declarative: the map's clear pattern. False for a
        motor whose family has no clear command (MIT)."""
        i = slave if isinstance(slave, int) else self.slave_index(slave)
        cfg = self.areas[i].slave.map.rawcan
        assert cfg is not None
        if self._od[i] is not None and cfg.odrive is not None:
            try:
                self._od_frame(i, "clear_errors", cfg.odrive.clear)
            except (can.CanError, OSError) as exc:
                raise self._io_failed("send", exc) from exc
            return True
        fam = self._fam_of.get(i)
        if fam is not None:  # its clear requests (answered: the code then in error_code)
            requests = list(fam.clear(i))
            if not requests or self._requests(requests):
                return False
            if (err := fam.error(i)) is not None and any(r.awaits for r in requests):
                self._codes[i] = err[0]
            return True
        return False

    def _seed_from_actual(self, i: int, within: str = "") -> None:
        """Motor ``i``'s set-points where it is: position as read, speed, torque and currents 0 (gains kept);
        only the channels whose names start with ``within`` (a mode's: ``"velocity."``)."""
        a = self.areas[i]
        img = self.groups[a.group].image
        out, inp = img.outputs.values[a.row], img.inputs.values[a.row]
        names, read = out.dtype.names or (), inp.dtype.names or ()
        for n in names:  # a mode's own channels too ("velocity.velocity": mode velocity's field)
            if not n.startswith(within):
                continue
            field = n.rpartition(".")[2]
            if field in ("velocity", "torque", "current", "duty", "brake_current"):
                out[n] = 0
            elif field == "position" and "position" in read:
                out[n] = inp["position"]

    def _send_raw(self, can_id: int, extended: bool, data: bytes) -> None:
        try:
            self._bus.send(self._message(arbitration_id=can_id, data=data, is_extended_id=extended))
        except (can.CanError, OSError) as exc:
            raise self._io_failed("send", exc) from exc

    def _answered(self, i: int, frame: bytes) -> bool:
        """Send ``frame`` on motor ``i``'s command id; True when its reply came (copied to its row)."""
        self._drain()
        self._arrived[i] = False
        self._send_raw(self._cmd[i][0].arbitration_id, False, frame)
        deadline = self._now() + ENTER_TIMEOUT_S
        try:
            while not self._arrived[i] and self._now() < deadline:
                self._accept(self._bus.recv(timeout=max(0.0, deadline - self._now())), copy=True)
        except (can.CanError, OSError) as exc:
            raise self._io_failed("receive", exc) from exc
        return bool(self._arrived[i])

    def _requests(self, requests: Any) -> list[int]:
        """Send a family's requests in order, each awaited reply within ``ENTER_TIMEOUT_S``; the motors that
        did not answer (a step unanswered ends the sequence)."""
        for req in requests:
            self._drain()
            for j in req.awaits:
                self._arrived[j] = False
            self._send_raw(*req.frame)
            if not req.awaits:
                continue
            deadline = self._now() + ENTER_TIMEOUT_S
            try:
                while not all(self._arrived[j] for j in req.awaits) and self._now() < deadline:
                    self._accept(self._bus.recv(timeout=max(0.0, deadline - self._now())), copy=True)
            except (can.CanError, OSError) as exc:
                raise self._io_failed("receive", exc) from exc
            missing = [j for j in req.awaits if not self._arrived[j]]
            if missing:
                return missing
        return []

    def _watch_errors(self) -> None:
        """Error codes of this cycle's replies: a new code outside ``ok_codes`` is a counted, named fault."""
        for i, fam in self._fam_of.items():
            if self._arrived[i] and (err := fam.error(i)) is not None and err[0] != self._codes[i]:
                if err[1] is not None:
                    self._fault(i, err[0], err[1])
                self._codes[i] = err[0]

    def _fault(self, i: int, code: int, name: str) -> None:
        """One fault onset of motor ``i``: counted, kept in :attr:`faults`, queued for :meth:`take_motor_events`."""
        self.motor_faults += 1
        self.faults.append(MotorFault(self._cycles, self.areas[i].slave.name, code, name))
        self._onsets.append((i, code, name))

    def take_motor_events(self, cycle: int) -> tuple[MotorFaultEvent, ...]:
        """The fault onsets since the last call as events of cycle ``cycle`` (the network's cycle index), each
        once; onsets seen during bring-up come with the first cycle. An empty tuple (no allocation) mostly."""
        if not self._onsets:
            return _NO_EVENTS
        out = []
        while self._onsets:
            i, code, name = self._onsets.popleft()
            a = self.areas[i]
            out.append(MotorFaultEvent(cycle, self.groups[a.group].name, a.row, a.slave.name, code, name))
        return tuple(out)

    # -- family odrive -------------------------------------------------------------------
    def _little(self, i: int) -> bool:
        cfg = self.areas[i].slave.map.rawcan
        return cfg is not None and cfg.byte_order == "little"

    def _od_of(self, i: int) -> odrive.OdriveProtocol | None:
        cfg = self.areas[i].slave.map.rawcan
        return cfg.odrive if cfg is not None else None

    def _odrive_init(self, i: int, cfg: Any, node: int) -> int:
        """Frames and routing of ODrive motor ``i``; returns the CAN id of its cyclic reply."""
        proto: odrive.OdriveProtocol = cfg.odrive
        if not 0 <= node < 0x40:
            raise FieldbusError(
                f"{self.areas[i].slave.name}: an ODrive node id is 0..63 (11-bit id = node << 5 | cmd)"
            )
        self._od_mode[i] = proto.mode_named(proto.mode)
        for m in proto.modes:
            self._od_msgs[i][m.command] = self._message(
                arbitration_id=node << 5 | m.command, data=bytearray(8), is_extended_id=False
            )
        reply_id = proto.can_id(node, "get_encoder_estimates")
        self._od_rtr[i] = self._message(
            arbitration_id=reply_id, is_remote_frame=True, dlc=8, is_extended_id=False
        )
        self._od_side[proto.can_id(node, "heartbeat")] = (i, "heartbeat")
        if proto.protocol == "0.6":
            self._od_side[proto.can_id(node, "get_error")] = (i, "get_error")
            self._od_side[proto.can_id(node, "txsdo")] = (i, "txsdo")
        at, offsets = 0, {}
        for f in cfg.reply:
            offsets[f.name] = at
            at += f.bits // 8
        self._od_at[i] = (offsets[proto.error_field], offsets[proto.state_field])
        return reply_id

    def _od_frame(self, i: int, command: str, data: bytes = b"", remote: bool = False) -> None:
        proto = self._od[i]
        assert proto is not None
        node = self.areas[i].slave.node_id or 0
        msg = self._message(
            arbitration_id=proto.can_id(node, command),
            data=data,
            is_remote_frame=remote,
            dlc=8 if remote else len(data),
            is_extended_id=False,
        )
        self._bus.send(msg)

    def _side_frame(self, msg: Any) -> bool:
        """A heartbeat, Get_Error or TxSdo frame of an ODrive: taken in (image, faults), True; else False."""
        got = self._od_side.get(msg.arbitration_id)
        if got is None or msg.is_remote_frame or msg.is_extended_id:
            return False
        i, kind = got
        data = bytes(msg.data)
        proto = self._od[i]
        assert proto is not None
        if kind == "heartbeat" and len(data) >= 5:
            error, state = odrive.heartbeat(data)
            row, (e_at, s_at) = self._reply_rows[i], self._od_at[i]
            row[e_at : e_at + 4] = np.frombuffer(data[:4], dtype=np.uint8)
            row[s_at] = state
            last = self._od_hb[i]
            self._od_hb[i] = (error, state)
            if error and (last is None or last[0] != error):
                self._fault(i, error, proto.error_names(error))
                if proto.protocol == "0.6":  # the detail: active errors and the disarm reason
                    self._od_frame(i, "get_error", remote=True)
        elif kind == "get_error" and len(data) == 8:
            self.active_errors[self.areas[i].slave.name] = (
                int.from_bytes(data[:4], "little"),
                int.from_bytes(data[4:], "little"),
            )
        elif kind == "txsdo":
            answer = odrive.sdo_reply(data)
            if answer is not None:
                self._sdo_answer = (i, *answer)
        return True

    def _await(self, done: Any, timeout_s: float) -> bool:
        """Receive (taking in side frames) until ``done()`` or the time-out; True when done."""
        deadline = self._now() + timeout_s
        try:
            while not done() and (left := deadline - self._now()) > 0:
                msg = self._bus.recv(timeout=left)
                if msg is not None and not msg.is_error_frame:
                    self._side_frame(msg)
        except (can.CanError, OSError) as exc:
            raise self._io_failed("receive", exc) from exc
        return bool(done())

    def _od_wait_heartbeat(self, i: int, state: int | None = None) -> None:
        proto = self._od[i]
        assert proto is not None
        timeout = max(ENTER_TIMEOUT_S, 3 * proto.heartbeat_ms / 1000)
        hb = self._od_hb

        def reached() -> bool:
            seen = hb[i]
            return seen is not None and (state is None or seen[1] == state)

        # ask for one now (RTR) rather than only wait for the next cyclic one: a heartbeat sent before this
        # bus listened, or drained at configure, is not repeated by a controller whose heartbeat timer is
        # slow or stopped; a firmware that ignores the request still sends its cyclic heartbeats
        try:
            self._od_frame(i, "heartbeat", remote=True)
        except (can.CanError, OSError) as exc:
            raise self._io_failed("send", exc) from exc
        if not self._await(reached, timeout):
            slave = self.areas[i].slave
            seen = hb[i]
            what = (
                "no heartbeat"
                if seen is None
                else f"axis state {seen[1]}, error {proto.error_names(seen[0])}"
            )
            raise StateTransitionError(
                f"bus '{self.bus.name}': {slave.name} (ODrive node {slave.node_id}) "
                + (f"did not reach axis state {state}: " if state is not None else "")
                + f"{what} within {timeout * 1000:.0f} ms",
                slave=slave.name,
            )

    def sdo(self, slave: int | str, endpoint: int, value: bytes | None = None) -> bytes:
        """Read (``value`` None) or write an ODrive endpoint through RxSdo (firmware 0.6); a write is
        confirmed by reading it back. Returns the 4 value bytes the controller answers. Blocking."""
        i = slave if isinstance(slave, int) else self.slave_index(slave)
        proto = self._od[i]
        if proto is None or proto.protocol != "0.6":
            raise FieldbusError(
                f"{self.areas[i].slave.name}: no endpoint access over CAN (ODrive firmware 0.6 only)"
            )
        self._drain()
        try:
            if value is not None:
                self._od_frame(i, "rxsdo", odrive.sdo_request(odrive.SDO_WRITE, endpoint, value))
            self._sdo_answer = None
            self._od_frame(i, "rxsdo", odrive.sdo_request(odrive.SDO_READ, endpoint))
        except (can.CanError, OSError) as exc:
            raise self._io_failed("endpoint access", exc) from exc
        if not self._await(
            lambda: self._sdo_answer is not None and self._sdo_answer[:2] == (i, endpoint), REGISTER_TIMEOUT_S
        ):
            raise BusTimeoutError(
                f"bus '{self.bus.name}': {self.areas[i].slave.name} did not answer the read of endpoint "
                f"{endpoint} within {REGISTER_TIMEOUT_S * 1000:.0f} ms"
            )
        assert self._sdo_answer is not None
        return self._sdo_answer[2]

    def _configure_odrive(self, i: int) -> None:
        """A heartbeat seen; Set_Controller_Mode for the map's mode; the map's endpoints written and read back."""
        proto, mode = self._od[i], self._od_mode[i]
        assert proto is not None and mode is not None
        self._drain()
        self._od_wait_heartbeat(i)
        try:
            self._od_frame(i, "set_controller_mode", odrive.controller_mode_frame(mode))
        except (can.CanError, OSError) as exc:
            raise self._io_failed("send", exc) from exc
        for item in proto.config:
            back = odrive.unpack_config(item, self.sdo(i, item.endpoint, odrive.pack_config(item)))
            if back != odrive.unpack_config(item, odrive.pack_config(item)):
                raise StateTransitionError(
                    f"bus '{self.bus.name}': {self.areas[i].slave.name} endpoint {item.name} ({item.endpoint}) "
                    f"reads back {back:g} after writing {item.value:g}",
                    slave=self.areas[i].slave.name,
                )

    def _od_request_state(self, i: int, state: int) -> None:
        self._od_frame(i, "set_axis_state", odrive.axis_state_frame(state))
        self._od_sent_state[i] = state

    def _op_odrive(self) -> None:
        """Every ODrive: CLOSED_LOOP_CONTROL requested (and written to the image's requested state), then
        awaited in the heartbeats."""
        for i, proto in enumerate(self._od):
            if proto is None:
                continue
            a = self.areas[i]
            self.groups[a.group].image.outputs.values[a.row][proto.request_field] = proto.closed_loop
            self._od_hb[i] = None  # the state is read from a heartbeat that comes after the request
            try:
                self._od_request_state(i, proto.closed_loop)
            except (can.CanError, OSError) as exc:
                raise self._io_failed("send", exc) from exc
            self._od_wait_heartbeat(i, proto.closed_loop)

    def _send_odrive(self, i: int, proto: odrive.OdriveProtocol) -> None:
        """One ODrive's cycle: Set_Axis_State when the image asks a new state; the set-point unless IDLE; the RTR."""
        row = self.out_row(i)  # the wire bytes (byte_order little: in frame order)
        want = odrive.requested_state(proto, row)
        if want and want != self._od_sent_state[i]:
            self._od_request_state(i, want)
        mode = self._od_mode[i]
        assert mode is not None
        if want != proto.idle:
            m = self._od_msgs[i][mode.command]
            odrive.encode_setpoint(mode, row, m.data)
            self._bus.send(m)
        self._bus.send(self._od_rtr[i])

    def configure(self) -> None:
        """Each family's configuration transaction (registers checked, written and read back); MIT
        motors of family ``mit`` have no registers: nothing to configure."""
        for fam in self._fams:
            self._transact(fam.configure())
        for i in range(self.n_slaves):
            if self._od[i] is not None:
                self._configure_odrive(i)

    def safe_op(self) -> None:
        """Nothing: motors stay out of motor mode until :meth:`op`."""

    def op(self) -> None:
        if self._odrives:
            self._op_odrive()
        missing = self._special("enter")
        if missing:
            raise StateTransitionError(
                f"bus '{self.bus.name}': no answer to enter-motor-mode from "
                + ", ".join(self.areas[i].slave.name for i in missing)
            )

    def _special(self, which: str) -> list[int]:
        """Send the enter/exit/zero frame to every motor; return the ones that did not answer.

        Raises :class:`~fieldbus.errors.BusIoError` when the driver fails.
        """
        self._drain()
        try:
            awaited: set[int] = set()
            for fam in self._fams:  # the families' requests (declarative: patterns, no answer awaited)
                reqs: list[Request] = list(fam.bring_up(which))
                for req in reqs:
                    can_id, ext, data = req.frame
                    self._bus.send(self._message(arbitration_id=can_id, data=data, is_extended_id=ext))
                    awaited.update(req.awaits)
            for i, area in enumerate(self.areas):
                cfg = area.slave.map.rawcan
                assert cfg is not None
                if self._fr[i]:
                    continue
                msg, _, _ = self._cmd[i]
                if cfg.odrive is not None:
                    if which == "clear":
                        self._od_frame(i, "clear_errors", cfg.odrive.clear)
                    elif which == "exit":
                        self._od_request_state(i, cfg.odrive.idle)
                    continue  # no answer to await: the heartbeat tells
                if which == "clear":
                    continue  # nothing to clear on this motor (families on the protocol clear their own)
                frame = getattr(cfg, which)
                self._bus.send(
                    self._message(arbitration_id=msg.arbitration_id, data=frame, is_extended_id=False)
                )
        except (can.CanError, OSError) as exc:
            raise self._io_failed("send", exc) from exc
        self._arrived.fill(False)
        for i, proto in enumerate(self._od):
            fam_done = self._fr[i] and i not in awaited
            self._arrived[i] = proto is not None or fam_done
        if which == "clear":
            for i in range(self.n_slaves):
                self._arrived[i] |= not self._fr[i]
        deadline = self._now() + ENTER_TIMEOUT_S
        try:
            while not self._arrived.all() and self._now() < deadline:
                self._accept(self._bus.recv(timeout=max(0.0, deadline - self._now())), copy=False)
        except (can.CanError, OSError) as exc:
            raise self._io_failed("receive", exc) from exc
        return [i for i in range(self.n_slaves) if not self._arrived[i]]

    def send(self) -> None:
        """One command frame per motor. Raises :class:`~fieldbus.errors.BusIoError` when the driver refuses one."""
        # What is still queued came after the last receive(): a reply there answers an earlier
        # command (late) and must not pass for this cycle's; it is counted and dropped.
        self._drain()
        try:
            for fam, msgs in self._fam_msgs:
                for c in fam.cycle():
                    m = msgs.get(id(c))
                    if m is None:  # first sent: its message, kept (the family keeps the frame)
                        m = msgs[id(c)] = self._message(
                            arbitration_id=c.can_id, data=c.data, is_extended_id=c.extended
                        )
                    m.arbitration_id = c.can_id  # a mode switch may move a frame (id + the mode's offset)
                    self._bus.send(m)
            for i, (msg, rev, data) in enumerate(self._cmd):
                if self._fr[i]:
                    continue
                proto = self._od[i]
                if proto is not None:
                    self._send_odrive(i, proto)
                    continue
                np.copyto(data, rev)
                self._bus.send(msg)
        except (can.CanError, OSError) as exc:
            raise self._io_failed("send", exc) from exc

    def receive(self) -> int | None:
        """Replies until every motor answered or the receive timeout.

        Raises :class:`~fieldbus.errors.BusIoError` (no motor arrived) when the driver fails.
        """
        self._arrived.fill(False)
        recv, accept, n = self._bus.recv, self._accept, len(self._reply_rows)
        clock = self._now
        deadline = clock() + self._timeout_s
        count = 0
        try:
            while count < n:
                remaining = deadline - clock()
                if remaining <= 0:
                    break
                count += accept(recv(timeout=remaining), copy=True)
        except (can.CanError, OSError) as exc:
            self._arrived.fill(False)
            raise self._io_failed("receive", exc) from exc
        self._cycles += 1
        if self._families:
            self._watch_errors()
        return count if count else None

    def _motor(self, msg: Any) -> int:
        """The motor whose reply ``msg`` is, or -1 (not a reply; error frames counted here)."""
        if msg.is_error_frame:
            self._error_frame(msg)
            return -1
        if self._odrives and self._side_frame(msg):
            return -1
        if msg.is_extended_id or msg.is_remote_frame:
            return -1
        can_id = msg.arbitration_id
        byte = self._node_byte.get(can_id)
        if byte is None:
            return -1
        data = msg.data
        return self._route.get((can_id, (data[byte] if byte < len(data) else -1) if byte >= 0 else -1), -1)

    def _accept(self, msg: Any, *, copy: bool) -> int:
        """Take ``msg`` as a reply; the number of motors it answered for (a shared frame: several)."""
        if msg is None:
            return 0
        if self._fams and not (msg.is_remote_frame or msg.is_error_frame):
            for fam in self._fams:
                motors = fam.carries(msg.arbitration_id, msg.is_extended_id, bytes(msg.data))
                if motors:
                    return self._accept_family(fam, motors, msg, copy=copy)
        i = self._motor(msg)
        if i < 0:
            return False
        if self._arrived[i]:
            self.extra_frames += 1
            return False
        if copy:
            row = self._reply_rows[i]
            data = msg.data
            n = self._reply_len[i]
            if len(data) != n:
                return False
            row[:n] = np.frombuffer(data, dtype=np.uint8)
        self._arrived[i] = True
        return True

    def _accept_family(self, fam: CanFamily, motors: Any, msg: Any, *, copy: bool) -> int:
        """A reply of a family on the protocol (one frame may carry several motors): into the rows of its
        motors when none of them has answered this cycle yet, else counted extra."""
        if any(self._arrived[i] for i in motors):
            self.extra_frames += 1
            return 0
        if copy:
            motors = fam.route(msg.arbitration_id, msg.is_extended_id, bytes(msg.data))
        for i in motors:
            self._arrived[i] = True
        return len(motors)

    def _family_carries(self, msg: Any) -> Sequence[int]:
        """The motors a family's reply ``msg`` is for (empty: no family's)."""
        if msg.is_remote_frame or msg.is_error_frame:
            return ()
        data = bytes(msg.data)
        for f in self._fams:
            if motors := f.carries(msg.arbitration_id, msg.is_extended_id, data):
                return motors
        return ()

    def _drain(self) -> None:
        """Drop every frame already queued: a motor's reply there is late, or extra when it had answered."""
        try:
            while (msg := self._bus.recv(timeout=0)) is not None:
                motors = self._family_carries(msg) if self._fams else ()
                if motors:  # a family's reply: extra when its motors answered this cycle, else late
                    if all(self._arrived[j] for j in motors):
                        self.extra_frames += 1
                    else:
                        self.late_frames += 1
                    continue
                i = self._motor(msg)
                if i >= 0:
                    if self._arrived[i]:
                        self.extra_frames += 1
                    else:
                        self.late_frames += 1
        except (can.CanError, OSError) as exc:
            raise self._io_failed("receive", exc) from exc

    def arrived(self) -> npt.NDArray[np.bool_]:
        return self._arrived

    def zero_position(self) -> list[str]:
        """Set the current position of every motor as zero; returns the motors that did not answer."""
        return [self.areas[i].slave.name for i in self._special("zero")]

    def stop(self) -> None:
        """Exit motor mode on every motor (a family on the protocol: its exit requests, safe frames first).
        Never raises: a failing bus is kept in :attr:`last_error`."""
        if self._bus is not None:
            try:
                self._special("exit")
            except Exception as exc:
                self._shut_failed("stop", exc)

    def close(self) -> None:
        """Close the bus (if this backend opened it) and its log, release the channel's lock.

        Idempotent; never raises: a failure is kept in :attr:`last_error`.
        """
        port, self._bus = self._bus, None
        try:
            release_can_bus(port, self._own_bus, self._log)
        except Exception as exc:
            self._shut_failed("close", exc)
        finally:
            if self._lock is not None:
                self._lock.release()
                self._lock = None
