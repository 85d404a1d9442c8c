"""A CAN bus between the master and in-process emulators, in one thread, on a virtual clock.

The master's end is a python-can-like bus (``send``, ``recv``, ``shutdown``)
handed to a CAN backend as its ``can_bus``. A frame the master sends is
handed at once to the emulators' ``deliver``; what they send back waits in
the master's queue. ``recv(timeout)`` with nothing queued lets time pass on
the clock, step by step (the emulators' timers run as it does), until a
frame comes or the timeout has passed. No thread, no wall time: the same
frames in the same order on every run.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from typing import Any

from fieldbus.platform.clock import VirtualClock

RECV_STEP_NS = 100_000  # a waiting master looks at its queue every 0.1 ms of virtual time


class LockstepPeer:
    """The emulators' end: what they ``send`` goes to the master's queue, stamped with the clock."""

    def __init__(self, bus: LockstepCanBus) -> None:
        self._bus = bus
        self.channel_info = f"lockstep peer of {bus.channel_info}"

    def send(self, msg: Any, timeout: float | None = None) -> None:
        msg.timestamp = self._bus.clock.now_ns() / 1e9
        self._bus.queue.append(msg)

    def recv(self, timeout: float | None = None) -> Any:
        return None  # frames reach the emulators through deliver(), never by polling

    def shutdown(self) -> None:
        pass


class LockstepCanBus:
    """The master's end of a lockstep CAN bus; ``deliver(msg)`` is every emulator's frame handler."""

    def __init__(self, clock: VirtualClock, channel: str = "lockstep") -> None:
        self.clock = clock
        self.channel_info = f"lockstep CAN '{channel}'"
        self.queue: deque[Any] = deque()
        self.handlers: list[Callable[[Any], None]] = []
        self.peer = LockstepPeer(self)
        self.sent = 0
        self.closed = False

    def send(self, msg: Any, timeout: float | None = None) -> None:
        """Hand ``msg`` to every emulator now (they answer into the master's queue)."""
        msg.timestamp = self.clock.now_ns() / 1e9
        self.sent += 1
        for handle in self.handlers:
            handle(msg)

    def recv(self, timeout: float | None = None) -> Any:
        """The next frame for the master; none queued: let up to ``timeout`` s pass on the clock for one."""
        if self.queue:
            return self.queue.popleft()
        if not timeout or timeout <= 0:
            return None
        # at least 1 ns: a caller's float remainder (1e-17 s) must still move time, or it waits forever
        deadline = self.clock.now_ns() + max(1, math.ceil(timeout * 1e9))
        while self.clock.now_ns() < deadline:
            self.clock.advance_to(min(deadline, self.clock.now_ns() + RECV_STEP_NS))
            if self.queue:
                return self.queue.popleft()
        return None

    def inject(self, msg: Any) -> None:
        """Put ``msg`` in the master's queue as if a node had sent it (error frames, foreign traffic)."""
        self.peer.send(msg)

    def fileno(self) -> int:
        raise NotImplementedError("a lockstep bus has no file descriptor")

    def shutdown(self) -> None:
        self.closed = True
