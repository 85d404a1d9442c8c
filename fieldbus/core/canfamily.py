"""The raw-CAN family protocol: one motor family's CAN protocol as a small sans-I/O object.

A family (``rawcan: family: <name>`` in a drive map) is a subclass of :class:`CanFamily`. The
raw-CAN backend keeps the transport (the interface lock, drain, deadlines, counters, error frames)
and talks to each family of its bus through these methods only; the family never sends, receives,
sleeps or reads a clock. One instance serves every motor of that family on one bus.

Directions: *command* frames go master -> motor (built from the process image's output rows, its
wire bytes: the image's ``to_wire`` already applied); *replies* go motor -> master (copied into the
input rows, which the image's ``from_wire`` decodes). A frame is ``(can id, extended, data)``.

Families are registered in one table, :func:`families`: the built-in ones plus every entry point of
group ``fieldbus.rawcan_families`` (``name = "package.module:FamilyClass"``), so a third party ships a
family as a package. The map loader, the backend, the bandwidth calculator and the emulators find a
family there and nowhere else.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Generator, Iterator, Sequence
from dataclasses import dataclass
from importlib import import_module
from importlib.metadata import entry_points
from typing import Any, ClassVar, NamedTuple, Protocol

from fieldbus.errors import FieldbusError

GROUP = "fieldbus.rawcan_families"
#: Built-in families ported to the protocol (every built-in one: the backend has no family paths of its own).
BUILTIN = {
    "frames": "fieldbus.core.canframes:FramesFamily",
    "mit": "fieldbus.core.mitfamily:MitFamily",
    "odrive": "fieldbus.core.odrivefamily:OdriveFamily",
    "damiao": "fieldbus.core.damiaofamily:DamiaoFamily",
    "cubemars": "fieldbus.core.cubemarsfamily:CubemarsFamily",
}

Frame = tuple[int, bool, bytes]  # (CAN id, extended 29-bit id, data; a Remote: a remote frame)


class Remote(bytes):
    """The data of a remote (RTR) frame: its length is the DLC asked for, its bytes are not sent."""


class FrameTime(NamedTuple):
    """One frame of a cycle for the bandwidth calculator: ``data_bytes`` on the wire, ``after``: the label
    of the frame it answers (a reply follows its command), or None (queued at the cycle's start)."""

    can_id: int
    data_bytes: int
    label: str
    extended: bool = False
    after: str | None = None
    shared: bool = False  # one frame for several motors of the bus: counted once (same id from each)
    remote: bool = False  # a remote (RTR) frame: no data field, classic CAN even on an FD bus
    period_us: float | None = None  # a background frame (a heartbeat) at most this often, not every cycle


@dataclass(frozen=True)
class FamilyMotor:
    """One motor of a family on a bus: the backend's slave ``index``, its ``node`` id, its map section as
    the family parsed it (``config``), and its image rows as uint8 arrays (``outputs``: the command's wire
    bytes; ``inputs``: where its replies go)."""

    index: int
    node: int
    config: Any
    outputs: Any
    inputs: Any
    name: str = ""  # the slave's name (for messages)


@dataclass(frozen=True)
class Request:
    """One step of a bring-up or recovery: send ``frame``, then await a reply from each motor index in
    ``awaits`` (empty: nothing to await, the next cycle's replies tell).

    With ``answer``: await the frame ``(can id, extended, data)`` for which it is true; its data is sent
    back into the generator (``data = yield request``). With ``until``: await, instead of a reply, the
    family's own condition (its state, as :meth:`CanFamily.take` and :meth:`CanFamily.route` leave it: "a
    heartbeat says closed loop"). Either at most ``timeout_s`` seconds (None: the backend's bring-up
    time-out); ``awaits`` then names the motors blamed when none came, ``what`` what they did not answer
    (the generator is not resumed). The backend runs a family's generator step by step: code after a
    ``yield`` sees the answer (a generator's ``return`` value is the result of an access). ``answer`` is
    for transactions (:data:`Steps`: configure, set_mode, register access, recover), its frame routed
    nowhere; :meth:`CanFamily.bring_up`'s requests are
    sent together and await replies (``awaits``) or conditions (``until``)."""

    frame: Frame
    awaits: tuple[int, ...] = ()
    answer: Callable[[int, bool, bytes], bool] | None = None
    until: Callable[[], bool] | None = None
    timeout_s: float | None = None
    what: str = ""


#: A transaction: a generator of requests (each sent, its answer or condition awaited), its return value
#: the transaction's result. It raises a FieldbusError (or :class:`StepRefused`) for a refused value.
Steps = Generator[Request, "bytes | None", Any]


class StepRefused(ValueError):
    """A step's answer refuses the map (a value that reads back otherwise): motor index ``motor``, the reason."""

    def __init__(self, motor: int, reason: str) -> None:
        super().__init__(reason)
        self.motor = motor


class ClassicSection(NamedTuple):
    """A classic ``rawcan:`` section as parsed so far, for :meth:`CanFamily.parse_section`: its ``path``,
    its ``mapping`` (every key, the family's own section among them or not), its command and reply fields
    (:class:`~fieldbus.core.rawcan_config.RawCanField`, frame order) and its ``byte_order``."""

    path: tuple[Any, ...]
    mapping: Any
    command: tuple[Any, ...]
    reply: tuple[Any, ...]
    byte_order: str


class CycleFrame(Protocol):
    """A command frame of the cycle; its ``data`` bytearray is rewritten in place by every
    :meth:`CanFamily.cycle`, so the transport builds its message around it once. An object with a true
    ``remote`` attribute goes out as a remote (RTR) frame asking for ``len(data)`` bytes."""

    can_id: int
    extended: bool
    data: bytearray


class CanFamily(ABC):
    """One family's protocol on one bus (sans I/O). Subclasses set :attr:`name` and implement the
    abstract methods; ``motors`` are the family's motors on the bus (:class:`FamilyMotor`).

    Raise ``ValueError`` from ``__init__`` for a bus the family cannot run (two motors in one slot, ...):
    the backend names the bus and refuses the configuration."""

    name: ClassVar[str]
    #: ``"module:Class"`` of the family's emulator (for the testing kit and the emulator process), or None:
    #: a class taking ``(bus, [(drive_map, node_id), ...], dt_s=, log=, clock=)`` (a python-can bus, the
    #: motors of the bus, a :class:`~fieldbus.platform.clock.Clock` or None), named, not imported: the
    #: emulators sit above fieldbus.
    emulator: ClassVar[str | None] = None
    #: The motors' register table when :meth:`register` reaches them (``lookup(text)`` -> a row with
    #: ``number``, ``name``, ``is_float``, ``read_only``, or an ``int`` outside the table, or None;
    #: ``REGISTERS``: the rows), else None (:mod:`fieldbus.core.damiao_registers` for Damiao).
    register_table: ClassVar[Any] = None
    #: The key of the family's own part of a classic ``rawcan:`` section (``rawcan.<section>``, parsed by
    #: :meth:`parse_section`; a map of another family refuses it), or None: the family has none.
    section: ClassVar[str | None] = None
    #: Most bits the command's and the reply's fields of a classic section take (a classic CAN frame: 64;
    #: a family whose image is more than one frame: more).
    max_bits: ClassVar[int] = 64
    #: Whether a classic section's big-endian reply may end in a float32 field that is not on the wire
    #: (a value the family computes, as an unwrapped multi-turn position).
    tail_float32: ClassVar[bool] = False

    def __init__(self, motors: Sequence[FamilyMotor]) -> None:
        self.motors = {m.index: m for m in motors}

    @classmethod
    @abstractmethod
    def parse(cls, r: Any, raw: Any, path: tuple[Any, ...]) -> tuple[Any, tuple[Any, ...], tuple[Any, ...]]:
        """The family's map section ``raw`` (``r``: the map loader's Reader, raising typed errors naming
        file, line, field): ``(config, rpdo, tpdo)``; the PDOs compile into the process image
        (rpdo = command = master outputs, tpdo = replies = master inputs)."""

    @classmethod
    def parse_section(cls, r: Any, classic: ClassicSection) -> Any:
        """The family's own part ``classic.mapping[section]`` of a classic section of this family, checked
        against the rest of it (``r``: the map loader's Reader): its config, kept in
        :attr:`~fieldbus.core.rawcan_config.RawCanConfig.sections`. Default: the part is required and kept
        as the map gives it."""
        if cls.section not in classic.mapping:
            raise r.err(classic.path, f"family {cls.name} needs its '{cls.section}' section")
        return classic.mapping[cls.section]

    @classmethod
    @abstractmethod
    def wire_frames(cls, name: str, config: Any, node: int) -> list[FrameTime]:
        """Motor ``name``'s frames of one cycle for the bandwidth calculator (a frame shared by several
        motors: ``shared``, the same ``(can_id, extended)`` from each, counted once per bus)."""

    @abstractmethod
    def cycle(self) -> Sequence[CycleFrame]:
        """The command frames of one cycle, their data from the motors' output rows (the family keeps its
        frame objects, data rewritten in place: no allocation per cycle). Which of them a cycle sends may
        change (a mode's or a packet's frame), and so may a frame's ``can_id``: the transport builds one
        message per frame object, the first time it is sent, and takes its id each cycle."""

    @abstractmethod
    def carries(self, can_id: int, extended: bool, data: bytes) -> Sequence[int]:
        """The motor indices a received frame is a reply of (empty: not this family's, or malformed);
        copies nothing (the transport counts late and extra replies with it)."""

    @abstractmethod
    def route(self, can_id: int, extended: bool, data: bytes) -> Sequence[int]:
        """Copy a reply into its motors' input rows; the motor indices it carried (as :meth:`carries`)."""

    @abstractmethod
    def commands(self, which: str, motor: int | None = None) -> list[Frame]:
        """The family's special frames ``which`` (``enable``, ``disable``, ``zero``, ``clear``) for every
        motor, or for motor index ``motor`` only; empty when the family has none."""

    @abstractmethod
    def stop_frames(self) -> list[Frame]:
        """The safe stop's command frames (the map's safe values, never the image: NaN-free)."""

    @abstractmethod
    def error(self, motor: int) -> tuple[int, str | None] | None:
        """Motor index ``motor``'s error code in its last reply (its input row) and the fault's name, None
        for a code that is no fault; None when the family reports no error code."""

    @classmethod
    def max_motors(cls, config: Any) -> int | None:
        """Most motors of this map one bus can hold (their CAN ids), None: no limit of the family's own."""
        return None

    def deadline_s(self, motor: int) -> float | None:
        """The most time, s after the cycle's command frames are handed to the driver, motor index
        ``motor``'s reply may take to count for its cycle (later: stale, counted late); None (the default):
        the bus's receive time-out."""
        return None

    def take(self, can_id: int, extended: bool, data: bytes) -> Sequence[int]:
        """A frame that is no cycle reply but the family's (a heartbeat, a status, an answer to a request),
        taken whenever it comes: its values into the motors' input rows, its answers into the family's
        state; the motors whose error code it may have changed (the backend checks :meth:`error` of
        each). Default: none."""
        return ()

    def set_mode(self, motor: int, mode: str) -> Steps:
        """Switch motor index ``motor`` to the map's mode ``mode``, between cycles: the requests; its
        commands go out in that mode from the next cycle. :class:`~fieldbus.errors.FieldbusError` (or
        ``ValueError``, the backend names the bus) for an unknown mode or a family without modes (the
        default)."""
        raise FieldbusError(f"family {self.name} has no modes")
        yield  # pragma: no cover - a generator

    def mode(self, motor: int) -> str | None:
        """The mode motor index ``motor``'s commands go out in (None: the family has no modes)."""
        return None

    @classmethod
    def register_key(
        cls, config: Any, reg: str, type_name: str | None, writing: bool
    ) -> tuple[int, str, str, bool]:
        """Register / endpoint ``reg`` as a user names it (a name of the map section ``config``, or a
        number; ``type_name``: the value type given, if any) for :meth:`access`: ``(key, label, value type
        - float32, uint32, int32 or bool -, read-only)``. ``ValueError`` saying what is wrong; the default:
        the family has no registers over CAN."""
        raise ValueError(f"family {cls.name} has no registers or endpoints over CAN")

    def access(self, motor: int, key: int, value: bytes | None = None) -> Steps:
        """Read (``value`` None) or write then read back a motor's register / endpoint ``key``: the
        requests; the generator returns the value bytes answered. ``ValueError`` when the family (the
        default) or this motor's firmware has none."""
        raise ValueError(f"family {self.name} has no registers or endpoints over CAN")
        yield  # pragma: no cover - a generator

    def configure(self) -> Steps:
        """The bring-up's transaction (registers checked and written, ...); default: nothing.
        :class:`StepRefused` for a motor whose answers refuse the map."""
        return
        yield

    def bring_up(self, which: str) -> Iterator[Request]:
        """The requests of a transition: ``enter`` (enable), ``exit`` (safe command, then disable),
        ``zero``, ``clear``. Default: the :meth:`commands` of ``which``, no answer awaited; ``exit`` sends
        :meth:`stop_frames` first."""
        if which == "exit":
            yield from (Request(f) for f in self.stop_frames())
        kind = {"enter": "enable", "exit": "disable"}.get(which, which)
        yield from (Request(f) for f in self.commands(kind))

    def recover(self, motor: int) -> Iterator[Request]:
        """Clear motor index ``motor``'s fault and enable it (the backend seeds its set-points from where
        it is first). Default: its ``clear`` then ``enable`` frames, no answer awaited."""
        for kind in ("clear", "enable"):
            yield from (Request(f) for f in self.commands(kind, motor))

    def clear(self, motor: int) -> Iterator[Request]:
        """Clear motor index ``motor``'s fault and leave it disabled. Default: its ``clear`` frames."""
        yield from (Request(f) for f in self.commands("clear", motor))

    def enabled(self, motor: int) -> bool:
        """After :meth:`recover`: whether the motor's last reply says it is enabled (default True)."""
        return True

    @classmethod
    def command_limits(cls, config: Any) -> list[tuple[str, float, float]]:
        """``(channel, min, max)`` windows of command channels the output rules saturate to, beyond the
        classic section's scaled fields (default none)."""
        return []

    @classmethod
    def emulator_kind(cls, config: Any) -> str:
        """The emulator kind of a motor with map section ``config``: motors of one kind share one emulator
        on a bus (default the family's name; a family whose emulators differ by protocol: one per protocol)."""
        return cls.name

    @classmethod
    def fault_codes(cls, config: Any) -> dict[int, str] | None:
        """The error codes this map's motors report as faults, by name (an emulator injects one of them);
        None: the family has no table of its own."""
        return None

    def register(self, motor: int, number: int, value: float | None = None, is_float: bool = False) -> Steps:
        """Read (``value`` None) or write a register: a transaction returning the value answered."""
        raise FieldbusError(f"family {self.name} has no registers")
        yield

    def save(self, motor: int) -> Steps:
        """Store the registers to flash (a transaction)."""
        raise FieldbusError(f"family {self.name} has no registers")
        yield


def families() -> dict[str, type[CanFamily]]:
    """The registered families by name: built-in ones, then entry points of group ``fieldbus.rawcan_families``
    (a built-in name is not replaced). Raises ``TypeError`` for an entry point that is no :class:`CanFamily`."""
    out: dict[str, type[CanFamily]] = {}
    for name, target in BUILTIN.items():
        module, _, attr = target.partition(":")
        out[name] = getattr(import_module(module), attr)
    for ep in entry_points(group=GROUP):
        if ep.name in out:
            continue
        cls = ep.load()
        if not (isinstance(cls, type) and issubclass(cls, CanFamily)):
            raise TypeError(f"entry point {ep.name} = {ep.value} of {GROUP} is not a CanFamily subclass")
        out[ep.name] = cls
    return out
