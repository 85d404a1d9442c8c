"""A topic whose first valid writer takes some axis groups: the claim of a client that cannot call services.

Nav2's ``cmd_vel`` and ros2_control's topic-based hardware interface only publish; they never claim,
enable or clear. :class:`TopicClaim` gives such a writer the served bus's rules: the first DDS
participant whose sample is valid claims the groups (in their gates, as ``<kind>:<its GUID>``) and
enables them; another participant's samples are refused whatever they say; a group claimed by a
client's request is not taken; when the owner's participant leaves the domain (or an operator claims a
group to clear a latch) the claim is let go. Nothing here moves a drive: the caller seeds the targets
until :attr:`TopicClaim.enabled`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from fieldbus.core.cia402 import Goal, State402
from fieldbus.dds.callers import Callers, publication_handle

if TYPE_CHECKING:
    from fieldbus.dds.parts import ServedGroup


class TopicClaim:
    """The claim of one topic's writer over ``groups`` (CiA 402 groups of the server)."""

    def __init__(self, kind: str, callers: Callers) -> None:
        self.kind = kind  # "cmd_vel", "joint_commands": how the gates name the owner
        self.callers = callers
        self.groups: list[ServedGroup] = []
        self.owner: str | None = None  # the owner's DDS participant GUID
        self.writer: tuple[Any, int] | None = None  # (reader, writer handle) it writes on
        self.takes = 0  # times a writer took the groups
        self._sequence = 0

    @property
    def ident(self) -> str:
        return f"{self.kind}:{self.owner}"

    def who(self, reader: Any, sample: Any) -> str | None:
        """The DDS participant that wrote ``sample`` (None: not known yet)."""
        return self.callers.of(reader, sample)

    def busy(self, groups: list[ServedGroup]) -> ServedGroup | None:
        """A group of ``groups`` a client holds by request (it cannot be taken), else None."""
        for g in groups:
            owner = g.gate.owner
            if owner is not None and not g.gate.latched and not owner.startswith(f"{self.kind}:"):
                return g
        return None

    def take(self, who: str, groups: list[ServedGroup]) -> None:
        """``who`` takes ``groups``: claims them (commands sent before do not apply) and enables them."""
        self.owner, self.groups, self.writer = who, list(groups), None
        self.takes += 1
        for g in self.groups:
            g.gate.claim(self.ident, f"{self.kind} ({who[:8]})")
            g.owner_writers = []  # watched here: the claim is let go, not latched
            g.discard_pending()
            if g.ctrl is not None and not g.gate.latched:
                g.ctrl.reset_fault_budget()
                g.ctrl.set_goal(Goal.ENABLE)

    def seen(self, reader: Any, sample: Any) -> None:
        """The owner wrote ``sample``: its writer's liveliness stands for the owner's."""
        self.writer = (reader, publication_handle(sample))

    def lost(self) -> str | None:
        """Why the claim must be let go (a group claimed by someone else, the owner gone), else None."""
        if self.owner is None:
            return None
        for g in self.groups:
            if g.gate.owner != self.ident:
                return f"group '{g.name}' was claimed by '{g.gate.label}'"
        if self.writer is not None and not self.callers.alive(*self.writer):
            return "the owner left the DDS domain"
        return None

    def let_go(self) -> None:
        """Release the groups (IDLE: their targets follow the joints); the next valid writer takes them."""
        for g in self.groups:
            if g.gate.owner == self.ident:
                g.gate.release(self.ident)
        self.owner, self.writer, self.groups = None, None, []

    @property
    def enabled(self) -> bool:
        """Every drive of the claimed groups OPERATION ENABLED, no group latched or stopped."""
        if self.owner is None:
            return False
        for g in self.groups:
            if g.gate.latched or g.stopped or g.ctrl is None:
                return False
            if not (g.ctrl.state == State402.OPERATION_ENABLED).all():
                return False
        return True

    def offer(self) -> None:
        """The owner commands this cycle: the gates see a command (their deadline starts over)."""
        self._sequence += 1
        for g in self.groups:
            g.gate.offer(self.ident, self._sequence)
