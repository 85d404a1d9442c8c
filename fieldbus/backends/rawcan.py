"""Raw-CAN backend on python-can: the transport of the motor families of one CAN bus.

Every motor runs on a family (:mod:`fieldbus.core.canfamily`, registered in
:func:`~fieldbus.core.canfamily.families`, a third party's through the ``fieldbus.rawcan_families``
entry points); the families build and decode the frames, this backend only moves them: the channel's
lock (:mod:`fieldbus.backends.buslock`: one master per channel), the drain, the deadlines, the counters,
error frames and a loop over the families' motors. Replies go to the motors through the bus's
:class:`~fieldbus.core.canroute.ReplyRouter`; a family's transactions (``configure()``,
:meth:`RawCanBackend.set_mode`, :meth:`RawCanBackend.register`, :meth:`RawCanBackend.access`, recovery)
run through :func:`~fieldbus.core.canrequests.run_requests`, each answer awaited, bounded; bring-up
(``op()``: ``enter``, ``stop()``: ``exit``, ``zero``, ``clear``) sends every family's requests together.

``receive()`` returns the number of replies that arrived (the "working counter" of a CAN cycle) and
``arrived()`` says which motors answered. A reply found queued at the next ``send()`` is late
(``late_frames``): it never passes for the next cycle's; a reply later than its family's ``deadline_s``
after the cycle's commands is stale (late, its motors' inputs held); a second reply of a motor in one
cycle is counted in ``extra_frames``. Driver errors raise :class:`~fieldbus.errors.BusIoError` and are
counted with error frames and bus-off (:class:`~fieldbus.backends.canfaults.CanFaults`); ``stop()`` and
``close()`` never raise.

A family's error code is watched (:mod:`fieldbus.core.motorfaults`): a rising code outside its
``ok_codes`` is one counted, named fault in :attr:`RawCanBackend.motor_faults` /
:attr:`RawCanBackend.faults`, and a :class:`MotorFaultEvent` in ``CycleResult.events`` once per onset
(:meth:`RawCanBackend.take_motor_events`, called by the network every cycle).

CAN FD: a bus with a ``data_bitrate`` (or ``can_options: {fd: true}``) sends every data frame as CAN FD,
with bit-rate switching when the data rate differs from the nominal one (remote frames stay classic).
"""

from __future__ import annotations

from collections import deque
from typing import Any

import numpy as np
import numpy.typing as npt

from fieldbus.backends.base import Backend
from fieldbus.backends.buslock import InterfaceLock, lock_can_bus
from fieldbus.backends.canbus import attach_can_bus, release_can_bus
from fieldbus.backends.canfaults import CanFaults
from fieldbus.core.canfamily import CanFamily, Frame, Remote, StepRefused, families
from fieldbus.core.canrequests import ENTER_TIMEOUT_S, Answer, run_bring_up, run_requests
from fieldbus.core.canroute import EXTRA, LATE, ReplyRouter, bus_motors
from fieldbus.core.hold import hold_row
from fieldbus.core.motorfaults import FAULT_LOG as FAULT_LOG
from fieldbus.core.motorfaults import FaultWatch, MotorFault, MotorFaultEvent, MotorPlace
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


class RawCanBackend(CanFaults, Backend):
    """The motors of one CAN bus (``interface`` = python-can channel), each on its family."""

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
        self._timeout_s = bus.receive_timeout_us / 1e6
        self._lock: InterfaceLock | None = None
        self._now = monotonic_s(
            options.get("clock")
        )  # seconds; in tests a virtual clock's (fieldbus.testing)
        places = [MotorPlace(a.slave.name, self.groups[a.group].name, a.row) for a in self.areas]
        self._watch = FaultWatch(places)  # error codes, fault onsets
        self.faults: deque[MotorFault] = self._watch.faults  # the newest kept, newest last
        self._cycles = 0
        rows = [(a.slave, self.out_row(i), self._in_rows[i]) for i, a in enumerate(self.areas)]
        declared = bus_motors(bus.name, rows)
        try:
            self._router = ReplyRouter.build(declared, families(), self.n_slaves, self._family_error)
        except ValueError as exc:
            raise FieldbusError(f"bus '{bus.name}': {exc}") from None
        self._fams = self._router.families
        self._fam_of = self._router.family_of
        self._arrived = self._router.arrived  # the motors that answered this cycle
        # the families' cycle frames by id(): a message built once around each (its data rewritten in place;
        # a family with modes sends another frame object after a switch, or moves a frame's id)
        self._fam_msgs: dict[int, Any] = {}
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
        return int(self._watch.codes[slave if isinstance(slave, int) else self.slave_index(slave)])

    def clear_errors(self) -> list[str]:
        """Send the clear-error frame to every motor that has one; returns the motors that did not answer. The
        motors stay disabled: :meth:`recover` clears one motor's fault and enables it again."""
        return [self.areas[i].slave.name for i in self._special("clear")]

    def recover(self, slave: int | str) -> bool:
        """Clear motor ``slave``'s fault and enable it again by its family's own sequence, between cycles
        (each answer awaited at most ``ENTER_TIMEOUT_S``); True when it is enabled again.

        First its set-points are seeded from where it is (position as read; velocity, torque and currents 0;
        the controller's gains kept: a motor holds where it is), so enabling starts no motion by
        itself: the controller writes its targets after.
        A family on the protocol: its recovery requests, each awaited answer or condition bounded (a
        clear-error frame, then enable, answered; a family without a clear command: enable, answered; declarative:
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
        self._watch.codes[i] = err[0] if (err := fam.error(i)) is not None else 0
        return True

    def clear_fault(self, slave: int | str) -> bool:
        """Clear motor ``slave``'s fault by its family's clear command and leave it disabled (outside a
        session: ``fieldbus register --clear-fault``; in one, :meth:`recover` also enables it). A family
        on the protocol: its clear requests, True when each awaited reply came (its code then in
        :meth:`error_code`; a request awaiting nothing: the next status tells; declarative: the map's clear
        pattern). False for a motor whose family has no clear command."""
        i = slave if isinstance(slave, int) else self.slave_index(slave)
        fam = self._fam_of.get(i)
        if fam is None:
            return False
        requests = list(fam.clear(i))
        if not requests or self._requests(requests):
            return False
        if (err := fam.error(i)) is not None and any(r.awaits for r in requests):
            self._watch.codes[i] = err[0]
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
        self._watch.seen(i, fam.error(i), self._cycles)

    @property
    def motor_faults(self) -> int:  # type: ignore[override]  # read-only here; an attribute on the base
        """Fault onsets since open, ever (the kept list :attr:`faults` is bounded)."""
        return self._watch.count

    def take_motor_events(self, cycle: int) -> tuple[MotorFaultEvent, ...]:
        """The fault onsets since the last call as events of cycle ``cycle`` (the network's cycle index), each
        once; onsets seen during bring-up come with the first cycle. An empty tuple (no allocation) mostly."""
        return self._watch.take(cycle)

    def configure(self) -> None:
        """Each family's ``configure`` transaction (registers or endpoints checked, written and read back, a
        status awaited); a family without registers has nothing to configure."""
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
        """Every family's ``which`` requests (enter, exit, zero, clear); return the motors that did not answer.

        Raises :class:`~fieldbus.errors.BusIoError` when the driver fails.
        """
        link = _Link(self, copy=False)
        missing, self._unmet = run_bring_up(self._fams, which, link, self._arrived, self._now)
        return missing  # _unmet: motor -> the condition it did not meet (its request's ``what``)

    def send(self) -> None:
        """One command frame per motor. Raises :class:`~fieldbus.errors.BusIoError` when the driver refuses one."""
        # What is still queued came after the last receive(): a reply there answers an earlier
        # command (late) and must not pass for this cycle's; it is counted and dropped.
        self._drain()
        if self._router.deadlines:
            self._router.sent_at = self._now()
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
        deadline = self._router.wait_until(clock() + self._timeout_s)  # every reply has its own: the last
        count = 0
        try:
            while count < n:
                remaining = deadline - clock()
                if remaining <= 0:
                    break
                count += accept(recv(timeout=remaining), copy=True)
        except (can.CanError, OSError) as exc:
            self._arrived.fill(False)
            self._router.sent_at = None
            raise self._io_failed("receive", exc) from exc
        self._cycles += 1
        self._router.sent_at = None
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
        n = self._router.reply(msg.arbitration_id, msg.is_extended_id, bytes(msg.data), self._now, copy=copy)
        if n >= 0:
            return n
        if n == EXTRA:
            self.extra_frames += 1
        else:
            self.late_frames += 1  # stale: its motors' inputs are held
        return 0

    def _drain(self) -> None:
        """Drop every frame already queued: a motor's reply there is late, or extra when it had answered."""
        try:
            while (msg := self._bus.recv(timeout=0)) is not None:
                if msg.is_error_frame:
                    self._error_frame(msg)
                elif not msg.is_remote_frame:
                    verdict = self._router.drained(msg.arbitration_id, msg.is_extended_id, bytes(msg.data))
                    if verdict == EXTRA:
                        self.extra_frames += 1
                    elif verdict == LATE:
                        self.late_frames += 1
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
