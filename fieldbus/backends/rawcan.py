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

Families on the protocol (:mod:`fieldbus.core.canfamily`, registered in :func:`~fieldbus.core.canfamily.families`,
a third party's through the ``fieldbus.rawcan_families`` entry points) are reached through it only: their
cycle frames, reply routing, status frames taken whenever they come (:meth:`~fieldbus.core.canfamily.CanFamily.take`:
a status whose error code changed is checked at once), bring-up steps (``configure``, ``enter``, ``exit``; a
step's condition awaited, bounded), transactions (:data:`~fieldbus.core.canfamily.Steps`: ``configure()``,
:meth:`RawCanBackend.set_mode`, :meth:`RawCanBackend.register`, :meth:`RawCanBackend.access`; each request's
answer awaited here, bounded), special and stop frames, recovery requests, error codes and reply deadlines (a reply later than its family's
``deadline_s`` after the cycle's commands is stale: counted late, its motors' inputs held). Family ``frames``
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
from fieldbus.core.canfamily import CanFamily, FamilyMotor, Frame, Remote, Request, StepRefused, families
from fieldbus.core.canrequests import ENTER_TIMEOUT_S, Answer, await_until, run_requests
from fieldbus.core.drivefault import DriveFault
from fieldbus.core.hold import hold_row
from fieldbus.core.network import Bus
from fieldbus.errors import BackendUnavailableError, BusTimeoutError, FieldbusError, StateTransitionError
from fieldbus.platform.clock import monotonic_s
from fieldbus.wire.canlog import open_log

try:
    import can
except ImportError as exc:  # pragma: no cover - depends on the install
    raise BackendUnavailableError(
        f"the rawcan backend needs python-can ({exc}): pip install 'fieldbus[can]'"
    ) from None

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
    error code outside its ``ok_codes`` (a new error), with the family's name for it.

    ``code`` is the family's own code (an error nibble, a family's error bits), not a CiA 402 0x603F.
    """

    reason: str = ""  # the family's name of ``code`` ("overload", "MOTOR_OVER_TEMP", ...)

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
        self._arrived = np.zeros(self.n_slaves, dtype=bool)
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
        declared: dict[str, list[FamilyMotor]] = {}  # the families of the bus: their motors
        for i, area in enumerate(self.areas):
            cfg = area.slave.map.rawcan
            if cfg is None or cfg.protocol is None:
                raise FieldbusError(
                    f"bus '{bus.name}': slave {area.slave.name} map {area.slave.map.name} has no rawcan family"
                )
            node = area.slave.node_id or 0
            motor = FamilyMotor(i, node, cfg.protocol, self.out_row(i), self._in_rows[i], area.slave.name)
            declared.setdefault(cfg.family, []).append(motor)
        registered = families()
        try:
            self._fams: list[CanFamily] = [registered[name](ms) for name, ms in declared.items()]
        except ValueError as exc:
            raise FieldbusError(f"bus '{bus.name}': {exc}") from None
        self._fam_of: dict[int, CanFamily] = {i: f for f in self._fams for i in f.motors}
        # the families' cycle frames by id(): a message built once around each (its data rewritten in place;
        # a family with modes sends another frame object after a switch, or moves a frame's id)
        self._fam_msgs: dict[int, Any] = {}
        # a family's reply deadline per motor (s after the cycle's commands; None: the receive time-out)
        self._reply_by: list[float | None] = [None] * self.n_slaves
        for i, fam in self._fam_of.items():
            self._reply_by[i] = fam.deadline_s(i)
        self._sent_at: float | None = None  # when this cycle's commands went out (while a deadline counts)
        by = [d for d in self._reply_by if d is not None]
        self._deadlines = bool(by)
        self._wait_cap = max(by) if len(by) == self.n_slaves else None  # every motor has a deadline: the last
        # last: a refused configuration above leaves no file open
        self._log = open_log(options.get("can_log"))  # every frame to a python-can log file

    @property
    def expected_wkc(self) -> int:
        """One reply per motor per cycle."""
        return self.n_slaves

    @property
    def late_replies(self) -> int:  # type: ignore[override]  # read-only here; an attribute on the base
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
        what = f"{'read' if value is None else 'write'} of register {register}"
        got: float = self._steps(self._registers_of(i).register(i, register, value, is_float), what, i)
        return got

    def save_registers(self, slave: int | str) -> None:
        """Store a motor's registers to its flash (a family's transaction: a motor may answer only while disabled).

        Blocking, outside the cycle. Raises :class:`~fieldbus.errors.BusTimeoutError` without an answer.
        """
        i = slave if isinstance(slave, int) else self.slave_index(slave)
        self._steps(self._registers_of(i).save(i), "save to flash", i)

    def _registers_of(self, i: int) -> CanFamily:
        fam = self._fam_of.get(i)
        if fam is None or fam.register_table is None:
            raise FieldbusError(f"{self.areas[i].slave.name}: its map's family has no registers over CAN")
        return fam

    def set_mode(self, slave: int | str, mode: str) -> None:
        """Switch a motor to ``mode`` (a mode name of its map) by its family's ``set_mode`` transaction
        (a mode register written and read back, a packet chosen, a controller mode sent), that mode's
        commands from the next cycle. Blocking: call it between
        cycles. The motor's set-points are then seeded where it is (position as read, speeds, torque and
        currents 0, gains kept), its mode's own channels (``<mode>.<field>``) too: the new mode starts no
        motion until the controller writes its targets, and a value left there from an earlier use of the
        mode is never sent (S12)."""
        i = slave if isinstance(slave, int) else self.slave_index(slave)
        fam = self._fam_of.get(i)
        if fam is None:
            raise FieldbusError(f"{self.areas[i].slave.name}: its map's family has no modes")
        self._steps(fam.set_mode(i, mode), "mode switch", i, timeout=StateTransitionError)
        self._seed_from_actual(i)  # the new mode starts where the motor is (S12)

    def mode(self, slave: int | str) -> str | None:
        """The mode a motor's commands are sent in (None: its family has no modes)."""
        i = slave if isinstance(slave, int) else self.slave_index(slave)
        fam = self._fam_of.get(i)
        return fam.mode(i) if fam is not None else None

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
        A family on the protocol: its recovery requests, each awaited answer or condition bounded (a
        clear-error frame, then enable, answered; MIT: enter motor mode, answered; declarative ``frames``:
        the map's clear and enable patterns, if any), then its
        :meth:`~fieldbus.core.canfamily.CanFamily.enabled` (the reply's code says enabled; a family without
        a clear command: only when its code is back to no fault, after a power cycle). Raises
        :class:`~fieldbus.errors.BusIoError` when the driver fails.
        """
        i = slave if isinstance(slave, int) else self.slave_index(slave)
        self._seed_from_actual(i)
        fam = self._fam_of[i]  # its recovery requests (declarative: the map's clear, enable)
        if self._requests(fam.recover(i)) or not fam.enabled(i):
            return False
        self._codes[i] = err[0] if (err := fam.error(i)) is not None else 0
        return True

    def clear_fault(self, slave: int | str) -> bool:
        """Clear motor ``slave``'s fault by its family's clear command and leave it disabled (outside a
        session: ``fieldbus register --clear-fault``; in one, :meth:`recover` also enables it). A family
        on the protocol: its clear requests, True when each awaited reply came (its code then in
        :meth:`error_code`; a request awaiting nothing: the next status tells; declarative: the map's clear
        pattern). False for a motor whose family has no clear command (MIT)."""
        i = slave if isinstance(slave, int) else self.slave_index(slave)
        fam = self._fam_of.get(i)
        if fam is None:
            return False
        requests = list(fam.clear(i))
        if not requests or self._requests(requests):
            return False
        if (err := fam.error(i)) is not None and any(r.awaits for r in requests):
            self._codes[i] = err[0]
        return True

    def _seed_from_actual(self, i: int) -> None:
        """Motor ``i``'s set-points where it is (:func:`~fieldbus.core.hold.hold_row`: position as read,
        speed, torque and currents 0, gains kept; each mode's own channels ``<mode>.<field>`` too); the
        output rules restart from them (S12)."""
        a = self.areas[i]
        img = self.groups[a.group].image
        hold_row(img.outputs.values[a.row], img.inputs.values[a.row])
        if self.on_hold is not None:
            self.on_hold(i)

    def _send_raw(self, can_id: int, extended: bool, data: bytes) -> None:
        try:
            self._bus.send(self._frame_message(can_id, extended, data))
        except (can.CanError, OSError) as exc:
            raise self._io_failed("send", exc) from exc

    def _frame_message(self, can_id: int, extended: bool, data: bytes) -> Any:
        """A family's frame as a python-can message (data :class:`~fieldbus.core.canfamily.Remote`: an RTR)."""
        if isinstance(data, Remote):
            return self._message(
                arbitration_id=can_id, is_remote_frame=True, dlc=len(data), is_extended_id=extended
            )
        return self._message(arbitration_id=can_id, data=data, is_extended_id=extended)

    def _cycle_message(self, c: Any) -> Any:
        """The message around a family's cycle frame ``c`` (its data bytearray shared; ``remote``: an RTR)."""
        if getattr(c, "remote", False):
            return self._message(
                arbitration_id=c.can_id, is_remote_frame=True, dlc=len(c.data), is_extended_id=c.extended
            )
        return self._message(arbitration_id=c.can_id, data=c.data, is_extended_id=c.extended)

    def _take(self, msg: Any) -> bool:
        """A family's status frame (not a cycle reply) taken in; a motor whose error code it changed is
        checked at once. False when no family takes it."""
        if msg.is_remote_frame or msg.is_error_frame:
            return False
        data = bytes(msg.data)
        for fam in self._fams:
            motors = fam.take(msg.arbitration_id, msg.is_extended_id, data)
            if motors:
                for i in motors:
                    self._family_error(i, fam)
                return True
        return False

    def _requests(self, requests: Any) -> list[int]:
        """Send a family's requests in order (:func:`~fieldbus.core.canrequests.run_requests`); the motors
        that did not answer."""
        return run_requests(requests, _Link(self, copy=True), self._arrived, self._now).missing

    def _receive_one(self, timeout_s: float, answer: Answer | None, copy: bool) -> bytes | None:
        """One frame within ``timeout_s``: its data when ``answer`` says it answers, else taken in, None."""
        try:
            msg = self._bus.recv(timeout=timeout_s)
        except (can.CanError, OSError) as exc:
            raise self._io_failed("receive", exc) from exc
        if msg is None:
            return None
        if answer is not None and not (msg.is_error_frame or msg.is_remote_frame):
            data = bytes(msg.data)
            if answer(msg.arbitration_id, msg.is_extended_id, data):
                return data
        self._accept(msg, copy=copy)
        return None

    def _steps(
        self, steps: Any, what: str, i: int | None = None, *, timeout: type[FieldbusError] = BusTimeoutError
    ) -> Any:
        """Run a family's steps (configure, a mode switch, an access) to their result; a step unanswered
        raises ``timeout`` (a transition's: :class:`~fieldbus.errors.StateTransitionError`), a refused
        answer :class:`~fieldbus.errors.StateTransitionError`, an unknown name
        :class:`~fieldbus.errors.FieldbusError`."""
        try:
            missing, req, result = run_requests(steps, _Link(self, copy=True), self._arrived, self._now)
        except StateTransitionError as exc:  # a family's refusal (a value read back otherwise, ...)
            raise StateTransitionError(f"bus '{self.bus.name}': {exc}", slave=exc.slave) from None
        except BusTimeoutError as exc:
            raise BusTimeoutError(f"bus '{self.bus.name}': {exc}") from None
        except StepRefused as exc:
            name = self.areas[exc.motor].slave.name
            raise StateTransitionError(f"bus '{self.bus.name}': {name} {exc}", slave=name) from None
        except ValueError as exc:
            who = self.areas[i].slave.name if i is not None else what
            raise FieldbusError(f"bus '{self.bus.name}': {who}: {exc}") from None
        if missing and req is not None:
            slave = self.areas[missing[0]].slave
            wait = req.timeout_s if req.timeout_s is not None else ENTER_TIMEOUT_S
            text = (
                f"bus '{self.bus.name}': {slave.name} (node {slave.node_id}) did not answer "
                f"{req.what or 'the ' + what} within {wait * 1000:.0f} ms"
            )
            raise (timeout(text, slave=slave.name) if timeout is StateTransitionError else timeout(text))
        return result

    def access(self, slave: int | str, key: int, value: bytes | None = None) -> bytes:
        """Read (``value`` None) or write a register / endpoint of a motor of a family on the protocol
        (its ``access`` steps: a write confirmed by reading it back); the value bytes the motor answers.
        Blocking, between cycles. :class:`~fieldbus.errors.BusTimeoutError` without an answer;
        :class:`~fieldbus.errors.FieldbusError` for a motor that has no such access."""
        i = slave if isinstance(slave, int) else self.slave_index(slave)
        fam = self._fam_of.get(i)
        if fam is None:
            raise FieldbusError(f"{self.areas[i].slave.name}: no register access of its family here")
        got: bytes = self._steps(fam.access(i, key, value), f"access to {key}", i)
        return got

    def family(self, slave: int | str) -> CanFamily | None:
        """The family object (:mod:`fieldbus.core.canfamily`) motor ``slave`` runs on, None when it runs on
        the backend's own paths (for its own state)."""
        return self._fam_of.get(slave if isinstance(slave, int) else self.slave_index(slave))

    def _watch_errors(self) -> None:
        """Error codes of this cycle's replies: a new code outside ``ok_codes`` is a counted, named fault."""
        for i, fam in self._fam_of.items():
            if self._arrived[i]:
                self._family_error(i, fam)

    def _family_error(self, i: int, fam: CanFamily) -> None:
        """Motor ``i``'s error code as its family reads it: a new fault code is one counted, named fault."""
        if (err := fam.error(i)) is not None and err[0] != self._codes[i]:
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

    def configure(self) -> None:
        """Each family's ``configure`` transaction (registers or endpoints checked, written and read back, a
        status awaited); MIT motors have no registers: nothing to configure."""
        for fam in self._fams:
            self._steps(fam.configure(), "configure", timeout=StateTransitionError)

    def safe_op(self) -> None:
        """Nothing: motors stay out of motor mode until :meth:`op`."""

    def op(self) -> None:
        missing = self._special("enter")
        if missing:
            raise StateTransitionError(
                f"bus '{self.bus.name}': no answer to enter-motor-mode from "
                + ", ".join(
                    self.areas[i].slave.name + (f" ({w})" if (w := self._unmet.get(i)) else "")
                    for i in missing
                ),
                slave=self.areas[missing[0]].slave.name,
            )

    def _special(self, which: str) -> list[int]:
        """Send the enter/exit/zero frame to every motor; return the ones that did not answer.

        Raises :class:`~fieldbus.errors.BusIoError` when the driver fails.
        """
        self._drain()
        self._unmet: dict[int, str] = {}  # motor -> the condition it did not meet (its request's ``what``)
        conditions: list[Request] = []  # requests whose condition is awaited (not a reply)
        try:
            awaited: set[int] = set()
            for fam in self._fams:  # the families' requests (declarative: patterns, no answer awaited)
                reqs: list[Request] = list(fam.bring_up(which))
                for req in reqs:
                    self._bus.send(self._frame_message(*req.frame))
                    if req.until is not None:
                        conditions.append(req)
                    else:
                        awaited.update(req.awaits)
        except (can.CanError, OSError) as exc:
            raise self._io_failed("send", exc) from exc
        self._arrived.fill(False)
        for i in range(self.n_slaves):
            self._arrived[i] = i not in awaited
        deadline = self._now() + max([ENTER_TIMEOUT_S, *(r.timeout_s or 0.0 for r in conditions)])

        def met() -> bool:
            return all(r.until() for r in conditions if r.until is not None)

        await_until(_Link(self, copy=False), self._now, deadline, lambda: bool(self._arrived.all()) and met())
        self._unmet = {
            j: r.what for r in conditions if r.until is not None and not r.until() for j in r.awaits
        }
        return [i for i in range(self.n_slaves) if not self._arrived[i] or i in self._unmet]

    def send(self) -> None:
        """One command frame per motor. Raises :class:`~fieldbus.errors.BusIoError` when the driver refuses one."""
        # What is still queued came after the last receive(): a reply there answers an earlier
        # command (late) and must not pass for this cycle's; it is counted and dropped.
        self._drain()
        if self._deadlines:
            self._sent_at = self._now()
        try:
            for fam in self._fams:
                for c in fam.cycle():
                    m = self._fam_msgs.get(id(c))
                    if m is None:  # once per frame object: its data bytearray is the message's
                        m = self._fam_msgs[id(c)] = self._cycle_message(c)
                    m.arbitration_id = c.can_id  # a mode switch may move a frame (id + the mode's offset)
                    self._bus.send(m)
        except (can.CanError, OSError) as exc:
            raise self._io_failed("send", exc) from exc

    def receive(self) -> int | None:
        """Replies until every motor answered or the receive timeout.

        Raises :class:`~fieldbus.errors.BusIoError` (no motor arrived) when the driver fails.
        """
        self._arrived.fill(False)
        recv, accept, n = self._bus.recv, self._accept, self.n_slaves
        clock = self._now
        deadline = clock() + self._timeout_s
        if self._wait_cap is not None and self._sent_at is not None:  # every reply has its own deadline
            deadline = min(deadline, self._sent_at + self._wait_cap)
        count = 0
        try:
            while count < n:
                remaining = deadline - clock()
                if remaining <= 0:
                    break
                count += accept(recv(timeout=remaining), copy=True)
        except (can.CanError, OSError) as exc:
            self._arrived.fill(False)
            self._sent_at = None
            raise self._io_failed("receive", exc) from exc
        self._cycles += 1
        self._sent_at = None
        self._watch_errors()
        return count if count else None

    def _accept(self, msg: Any, *, copy: bool) -> int:
        """Take ``msg`` as a reply; the number of motors it answered for (a shared frame: several)."""
        if msg is None:
            return 0
        if msg.is_error_frame:
            self._error_frame(msg)
            return 0
        if msg.is_remote_frame:
            return 0
        for fam in self._fams:
            motors = fam.carries(msg.arbitration_id, msg.is_extended_id, bytes(msg.data))
            if motors:
                return self._accept_family(fam, motors, msg, copy=copy)
        self._take(msg)
        return 0

    def _accept_family(self, fam: CanFamily, motors: Any, msg: Any, *, copy: bool) -> int:
        """A reply of a family on the protocol (one frame may carry several motors): into the rows of its
        motors when none of them has answered this cycle yet, else counted extra."""
        if any(self._arrived[i] for i in motors):
            self.extra_frames += 1
            return 0
        if copy and self._sent_at is not None and self._past_deadline(motors):
            self.late_frames += 1  # stale: its motors' inputs are held
            return 0
        if copy:
            motors = fam.route(msg.arbitration_id, msg.is_extended_id, bytes(msg.data))
        for i in motors:
            self._arrived[i] = True
        return len(motors)

    def _past_deadline(self, motors: Any) -> bool:
        """A reply of ``motors`` now is past the reply deadline of one of them (a shared frame: any)."""
        assert self._sent_at is not None
        now = self._now()
        return any((d := self._reply_by[i]) is not None and now > self._sent_at + d for i in motors)

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
                if msg.is_error_frame:
                    self._error_frame(msg)
                elif motors := self._family_carries(msg):  # extra when its motors answered, else late
                    if all(self._arrived[j] for j in motors):
                        self.extra_frames += 1
                    else:
                        self.late_frames += 1
                else:
                    self._take(msg)
        except (can.CanError, OSError) as exc:
            raise self._io_failed("receive", exc) from exc

    def arrived(self) -> npt.NDArray[np.bool_]:
        return self._arrived

    def zero_position(self) -> list[str]:
        """Set the current position of every motor as zero; returns the motors that did not answer."""
        return [self.areas[i].slave.name for i in self._special("zero")]

    def stop(self) -> None:
        """Exit motor mode on every motor (a family on the protocol: its exit requests, its safe stop frames
        first: a zero command in the motor's mode, or no current).
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


class _Link:
    """The backend's bus as the request runner's :class:`~fieldbus.core.canrequests.Link` (``copy``: replies
    go into the motors' input rows)."""

    def __init__(self, backend: RawCanBackend, *, copy: bool) -> None:
        self._backend = backend
        self._copy = copy

    def drain(self) -> None:
        self._backend._drain()

    def send(self, frame: Frame) -> None:
        self._backend._send_raw(*frame)

    def receive(self, timeout_s: float, answer: Answer | None) -> bytes | None:
        return self._backend._receive_one(timeout_s, answer, self._copy)
