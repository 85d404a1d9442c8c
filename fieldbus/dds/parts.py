"""What the server's parts (the ``cmd_vel`` base, a topic claim, the joint topics) see of it, as protocols.

:class:`~fieldbus.dds.server.BusServer` creates its parts and calls them every
cycle; they name here what they read of the server and of a served group, so
they do not import the server (``server.py`` satisfies these; mypy checks it
where the server hands itself over).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any, Protocol

if TYPE_CHECKING:
    from fieldbus.core.cia402 import Cia402Controller
    from fieldbus.core.pdo.image import ProcessImage
    from fieldbus.dds.callers import Callers
    from fieldbus.dds.gate import CommandGate
    from fieldbus.dds.participant import Participant


class ServedGroup(Protocol):
    """One axis group as served: its gate, its CiA 402 controller, its roles' channels."""

    owner_writers: list[tuple[Any, int]]  # (reader, writer handle) the owner was seen on; a claim resets it

    @property
    def name(self) -> str: ...
    @property
    def axes(self) -> tuple[str, ...]: ...
    @property
    def image(self) -> ProcessImage: ...
    @property
    def gate(self) -> CommandGate: ...
    @property
    def ctrl(self) -> Cia402Controller | None: ...
    @property
    def out_roles(self) -> dict[str, str]: ...  # role (position, velocity, ...) -> output channel
    @property
    def in_roles(self) -> dict[str, str]: ...  # role -> input channel
    @property
    def stopped(self) -> bool: ...  # held by safe outputs
    def discard_pending(self) -> None: ...


class BusServer(Protocol):
    """The server as its parts see it: its groups, its callers, its participant."""

    @property
    def groups(self) -> Mapping[str, ServedGroup]: ...
    @property
    def callers(self) -> Callers: ...
    @property
    def participant(self) -> Participant: ...
