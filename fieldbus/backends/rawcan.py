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
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from fieldbus.backends.base import Backend
from fieldbus.backends.buslock import InterfaceLock, lock_can_bus
from fieldbus.backends.canbus import attach_can_bus, release_can_bus
from fieldbus.backends.canfaults import CanFaults
from fieldbus.backends.canlog import open_log
from fieldbus.core.network import Bus
from fieldbus.errors import BackendUnavailableError, FieldbusError, StateTransitionError
from fieldbus.runtime.clock import monotonic_s

try:
    import can
except ImportError as exc:  # pragma: no cover - depends on the install
    raise BackendUnavailableError(
        f"the rawcan backend needs python-can ({exc}): pip install 'fieldbus[can]'"
    ) from None

ENTER_TIMEOUT_S = 0.5


class RawCanBackend(CanFaults, Backend):
    """MIT-mode motors on one CAN bus (``interface`` = python-can channel)."""

    kind = "rawcan"
    pdo_align = 8

    def __init__(self, bus: Bus, **options: Any) -> None:
        super().__init__(bus, **options)
        self._bus: Any = options.get("can_bus")  # tests may hand in a bus instance
        self._own_bus = self._bus is None
        self._cmd: list[tuple[Any, npt.NDArray[np.uint8], npt.NDArray[np.uint8]]] = []
        self._route: dict[tuple[int, int], int] = {}  # (can id, node byte or -1) -> slave index
        self._node_byte: dict[int, int] = {}  # reply CAN id -> index of the node byte in the frame, or -1
        self._arrived = np.zeros(self.n_slaves, dtype=bool)
        # each motor's reply bytes as the frame has them: its input row, reversed (a view)
        self._reply_rows = [self.in_row(i)[::-1] for i in range(self.n_slaves)]
        self._timeout_s = bus.receive_timeout_us / 1e6
        self._lock: InterfaceLock | None = None
        self._now = monotonic_s(
            options.get("clock")
        )  # seconds; in tests a virtual clock's (fieldbus.testing)
        for i, area in enumerate(self.areas):
            cfg = area.slave.map.rawcan
            if cfg is None:
                raise FieldbusError(
                    f"bus '{bus.name}': slave {area.slave.name} map {area.slave.map.name} has no rawcan section"
                )
            node = area.slave.node_id or 0
            out_row = self.out_row(i)
            msg = can.Message(
                arbitration_id=cfg.command_id + node, data=bytearray(out_row.size), is_extended_id=False
            )
            # the frame's data bytearray seen as a numpy array: encoding writes straight into it
            self._cmd.append((msg, out_row[::-1], np.frombuffer(msg.data, dtype=np.uint8)))
            reply_id = cfg.reply_id if cfg.reply_id is not None else cfg.command_id + node
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

    def configure(self) -> None:
        """MIT-mode motors have no object dictionary: nothing to configure."""

    def safe_op(self) -> None:
        """Nothing: motors stay out of motor mode until :meth:`op`."""

    def op(self) -> None:
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
            for i, area in enumerate(self.areas):
                cfg = area.slave.map.rawcan
                assert cfg is not None
                msg, _, _ = self._cmd[i]
                self._bus.send(
                    can.Message(
                        arbitration_id=msg.arbitration_id, data=getattr(cfg, which), is_extended_id=False
                    )
                )
        except (can.CanError, OSError) as exc:
            raise self._io_failed("send", exc) from exc
        self._arrived.fill(False)
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
            for msg, rev, data in self._cmd:
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
                if accept(recv(timeout=remaining), copy=True):
                    count += 1
        except (can.CanError, OSError) as exc:
            self._arrived.fill(False)
            raise self._io_failed("receive", exc) from exc
        return count if count else None

    def _motor(self, msg: Any) -> int:
        """The motor whose reply ``msg`` is, or -1 (not a reply; error frames counted here)."""
        if msg.is_error_frame:
            self._error_frame(msg)
            return -1
        if msg.is_extended_id or msg.is_remote_frame:
            return -1
        can_id = msg.arbitration_id
        byte = self._node_byte.get(can_id)
        if byte is None:
            return -1
        data = msg.data
        return self._route.get((can_id, (data[byte] if byte < len(data) else -1) if byte >= 0 else -1), -1)

    def _accept(self, msg: Any, *, copy: bool) -> bool:
        if msg is None:
            return False
        i = self._motor(msg)
        if i < 0:
            return False
        if self._arrived[i]:
            self.extra_frames += 1
            return False
        if copy:
            row = self._reply_rows[i]
            data = msg.data
            if len(data) != row.size:
                return False
            row[:] = np.frombuffer(data, dtype=np.uint8)
        self._arrived[i] = True
        return True

    def _drain(self) -> None:
        """Drop every frame already queued: a motor's reply there is late, or extra when it had answered."""
        try:
            while (msg := self._bus.recv(timeout=0)) is not None:
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
        """Exit motor mode on every motor. Never raises: a failing bus is kept in :attr:`last_error`."""
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
