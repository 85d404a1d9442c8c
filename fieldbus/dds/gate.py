"""The door for commands that come from another process: one owner, ordered sequences, a deadline.

Pure and counted in cycles (no clock, no DDS): :class:`CommandGate` decides,
once per bus cycle, whether a group's newest command is applied, held or
replaced by the safe stop. The rules (``docs/dds.md``):

- **one owner**: a client commands a group only after ``claim``; a second
  client's claim is refused (:class:`ClaimError`) while the owner is alive,
  i.e. until the owner's deadline has latched the safe stop; commands from
  anyone but the owner are refused and counted. The server names a client by
  its DDS participant (the GUID of the writer's participant, from the sample
  info), never by a string inside the sample.
- **ordered**: a sequence number not above the owner's last one is dropped and
  counted (a late or duplicated sample; a new claim starts a new sequence).
- **deadline**: after the first command, ``hold_after`` cycles with no new one
  put the group in HOLD (the last command stays applied); ``stop_after``
  cycles latch SAFE_STOP (the group's safe outputs every cycle), which only an
  explicit :meth:`CommandGate.clear` by the owner opens. An owner that sends
  no command at all (IDLE after its claim, clear or enable) latches the same
  stop ``stop_after`` cycles later, so a client that dies before its first
  command does not hold the group: it becomes claimable again. A procedure
  the server drives (:meth:`CommandGate.pause`) stops that count until
  :meth:`CommandGate.resume`.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

from fieldbus.errors import FieldbusError

VERBS = (
    "describe",
    "claim",
    "release",
    "enable",
    "disable",
    "clear_safe_stop",
    "reset_faults",
    "home",
    "mode",
    "sdo_read",
    "sdo_write",
    "set_odometry",
)
"""What a :class:`~fieldbus.dds.messages.Request` may ask."""


class ClaimError(FieldbusError):
    """A client may not command this group: another client owns it, or this one has not claimed it."""


class GateState(IntEnum):
    """A group's command state as published in ``AxisState.gate``."""

    IDLE = 0  # no command since the claim, clear or enable: targets follow the joints (no motion)
    COMMANDED = 1  # the newest command is younger than hold_after cycles
    HOLD = 2  # no new command for hold_after cycles: the last one stays applied
    SAFE_STOP = 3  # no new command for stop_after cycles: safe outputs, latched until clear


@dataclass(frozen=True)
class Deadline:
    """Cycles without a new command before HOLD and before SAFE_STOP (``1 <= hold_after < stop_after``)."""

    hold_after: int = 20
    stop_after: int = 200

    def __post_init__(self) -> None:
        for what, v in (("hold_after", self.hold_after), ("stop_after", self.stop_after)):
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise FieldbusError(
                    f"command deadline {what} must be a whole number of cycles >= 1, not {v!r}"
                )
        if self.stop_after <= self.hold_after:
            raise FieldbusError(
                f"command deadline stop_after ({self.stop_after}) must be more cycles than hold_after "
                f"({self.hold_after})"
            )


class CommandGate:
    """One axis group's command door; call :meth:`offer` for each command received, then :meth:`tick` once."""

    def __init__(self, deadline: Deadline) -> None:
        self.deadline = deadline
        self.owner: str | None = None  # the owner's identity (the server: its DDS participant's GUID)
        self.label = ""  # the owner's name as it gave it (its client_id), for people
        self.state = GateState.IDLE
        self.last_sequence = 0  # the owner's newest accepted sequence number
        self.applied_sequence = 0  # the newest command applied to the outputs (0: none)
        self.age = 0  # cycles since the newest accepted command
        self.dropped = 0  # commands dropped because their sequence number did not increase
        self.refused = 0  # commands from a client that does not own the group
        self._fresh = False  # a command was accepted since the last tick
        self.paused = False  # a procedure the server drives: no deadline while IDLE

    @property
    def latched(self) -> bool:
        return self.state is GateState.SAFE_STOP

    def claim(self, client: str, label: str | None = None) -> None:
        """Make ``client`` the owner (``label``: its name for people, default ``client``); :class:`ClaimError`
        while another live client owns the group. Not latched: IDLE (no command applies until the next)."""
        if self.owner == client:
            return
        if self.owner is not None and not self.latched:
            raise ClaimError(f"the group is commanded by client '{self.label}': claim refused")
        self.owner = client
        self.label = client if label is None else label
        self.last_sequence = 0
        self._idle()

    def _idle(self) -> None:
        """No command applies until the next one (unless latched); the no-command deadline restarts."""
        if not self.latched:
            self.state = GateState.IDLE
        self.age = 0
        self._fresh = False
        self.paused = False

    def restart(self, client: str) -> None:
        """The owner enabled the drives: IDLE (commands sent before it no longer apply), deadline restarts."""
        self._check_owner(client)
        self._idle()

    def heard_from(self, client: str) -> None:
        """A request from ``client``: if it owns the IDLE group, it is alive, and the no-command deadline
        restarts (a COMMANDED group's deadline is kept by commands only)."""
        if client == self.owner and self.state is GateState.IDLE:
            self.age = 0

    def latch(self) -> None:
        """Latch SAFE_STOP now (a bus's safe stop or a drive fault): the owner must clear it."""
        self.state = GateState.SAFE_STOP
        self._fresh = False

    def release(self, client: str) -> None:
        """``client`` gives the group up; the last command stays applied, with no deadline (IDLE)."""
        self._check_owner(client)
        self.owner = None
        self.label = ""
        self._idle()

    def check_owner(self, client: str) -> None:
        """:class:`ClaimError` unless ``client`` owns the group."""
        self._check_owner(client)

    def _check_owner(self, client: str) -> None:
        if self.owner != client:
            held = f"owned by client '{self.label}'" if self.owner is not None else "not claimed"
            raise ClaimError(f"client '{client}' has not claimed the group ({held})")

    def offer(self, client: str, sequence: int) -> bool:
        """A command arrived; True when it is to be applied now (owner, newer, not latched)."""
        if client != self.owner:
            self.refused += 1
            return False
        if sequence <= self.last_sequence:
            self.dropped += 1
            return False
        self.last_sequence = sequence
        if self.latched:
            return False
        self.applied_sequence = sequence
        self._fresh = True
        self.paused = False
        return True

    def tick(self) -> GateState:
        """End of this cycle's offers: advance the deadline; returns the state for this cycle."""
        if self.latched:
            return self.state
        if self._fresh:
            self._fresh = False
            self.age = 0
            self.state = GateState.COMMANDED
        elif self.state is not GateState.IDLE or (self.owner is not None and not self.paused):
            self.age += 1
            if self.age >= self.deadline.stop_after:
                self.state = GateState.SAFE_STOP
            elif self.age >= self.deadline.hold_after and self.state is not GateState.IDLE:
                self.state = GateState.HOLD
        return self.state

    def pause(self, client: str) -> None:
        """The owner starts a procedure the server drives (homing, a mode switch): IDLE, no deadline,
        until the owner's next command; :class:`ClaimError` if not the owner, refused while latched."""
        self._check_owner(client)
        if self.latched:
            raise ClaimError("safe stop latched: send clear_safe_stop first")
        self._idle()
        self.paused = True

    def resume(self) -> None:
        """The procedure ended: the no-command deadline counts again, from now."""
        self.paused = False
        self.age = 0

    def clear(self, client: str) -> None:
        """The owner opens the latch; the group is IDLE until its next command."""
        self._check_owner(client)
        self.state = GateState.IDLE
        self._idle()
