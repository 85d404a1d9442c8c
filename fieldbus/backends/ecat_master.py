"""The one adapter between fieldbus and pysoem (SOEM): opening a card, SDOs, states and registers, our errors.

The EtherCAT backend, the EtherCAT scan and ``fieldbus sdo`` use these and
nothing else of pysoem's error surface, so a pysoem error means the same
wherever it appears:

- opening a card that cannot be opened: :class:`~fieldbus.errors.FieldbusError`
  naming the card(s) and saying raw sockets need root or CAP_NET_RAW;
- an SDO abort: :class:`~fieldbus.errors.SdoAbortError` (code, object, slave);
  no answer (pysoem ``WkcError``, ``MailboxError``, ``PacketError``): tried
  again, then :class:`~fieldbus.errors.BusTimeoutError`; an emergency that came
  instead of the answer: handed to the caller, the transfer tried again;
- a state not reached: :class:`~fieldbus.errors.StateTransitionError` with
  each slave's state and AL status code;
- SDO Information (pysoem's ``slave.od``) that fails: FieldbusError, and SOEM's
  queue of SDO Information errors emptied either way;
- a register read or write without answer: ``None`` / ``False`` (one frame;
  the caller decides whether to try again).

Recovery is not here: it is the backend's one state machine of bounded steps
(:meth:`fieldbus.backends.ethercat.EthercatBackend._recover`, its position-addressed
frames in :mod:`.ecat_raw`); its register frames at the station address go
through :class:`SoemPort`.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Collection, Iterator, Sequence
from typing import Any, Protocol

from fieldbus.core.al import AL_ERROR, al_status_name, state_name
from fieldbus.errors import (
    BackendUnavailableError,
    BusTimeoutError,
    FieldbusError,
    SdoAbortError,
    StateTransitionError,
)

try:
    import pysoem as pysoem  # the backend takes it from here: one check that pysoem is installed
except ImportError as exc:  # pragma: no cover - depends on the install
    raise BackendUnavailableError(
        f"EtherCAT needs pysoem ({exc}): pip install 'fieldbus[ethercat]'"
    ) from None

# pysoem's errors that mean "no answer" (a lost or late frame, a mailbox that did not reply)
NO_ANSWER: tuple[type[Exception], ...] = (pysoem.WkcError, pysoem.MailboxError, pysoem.PacketError)
NO_FRAME_ANSWER: tuple[type[Exception], ...] = (pysoem.WkcError, pysoem.PacketError)  # a register frame
STATE_CODES = {"INIT": 1, "PRE-OP": 2, "SAFE-OP": 4, "OP": 8}  # AL state codes by name (ETG.1000.6)


def describe(exc: BaseException) -> str:
    """An exception as a reason: its message, or its type when it has none (pysoem's WkcError)."""
    text = str(exc)
    return (
        f"{type(exc).__name__}: {text}"
        if text
        else f"{type(exc).__name__} (no answer at the slave's address)"
    )


def open_card(master: Any, interface: str, redundant: str | None = None, *, where: str = "") -> None:
    """``master.open`` on ``interface`` (and the ``redundant`` port); FieldbusError naming the cards."""
    try:
        if redundant:
            master.open(interface, redundant)
        else:
            master.open(interface)
    except Exception as exc:
        cards = " and ".join(f"'{p}'" for p in (interface, redundant) if p)
        raise FieldbusError(
            f"{where}cannot open interface {cards} ({exc}); "
            "raw sockets need root (or CAP_NET_RAW) and the link must be up"
        ) from exc


SCAN_TRIES = 8  # config_init runs this often before a segment counts as empty (about 0.4 s)


def find_slaves(
    master: Any, *, wait_s: float = 0.0, clock: Callable[[], float] = time.monotonic
) -> list[Any]:
    """SOEM's ``config_init`` (station addresses, SII, PRE-OP requested): the slaves found, in wire order.

    SOEM counts the slaves with one broadcast read and waits 20 ms for it (EC_TIMEOUTSAFE): one lost
    frame would read as an empty segment, and so would a machine that holds the master or the slaves'
    process for tens of milliseconds (a loaded VM held an emulator's replies over three scans). A scan
    that finds nobody is made again, ``SCAN_TRIES`` in all (an empty segment costs about 0.4 s: a scan
    sends about 6 frames in 48 ms at SOEM's default timeouts, measured on veth), and further until
    ``wait_s`` [s, ``clock``'s] have passed (a device restarting after a firmware update); an empty
    list after that.
    """
    deadline = clock() + wait_s
    tries = 0
    while tries < SCAN_TRIES or clock() < deadline:
        tries += 1
        if int(master.config_init()) > 0:
            return list(master.slaves)
    return []


def open_segment(interface: str, *, wait_s: float = 0.0) -> Any:
    """A pysoem Master on ``interface`` with its slaves found and their states read (a tool's master: scan,
    ``fieldbus sdo``). FieldbusError when the card cannot be opened or no slave answers (``wait_s``: how
    long to keep scanning for one, see :func:`find_slaves`). Close it when done."""
    master = pysoem.Master()
    open_card(master, interface)
    if not find_slaves(master, wait_s=wait_s):
        master.close()
        raise FieldbusError(f"no EtherCAT slave answers on '{interface}' (is the cable in and the link up?)")
    master.read_state()
    return master


def sdo(
    call: Callable[[], Any],
    *,
    index: int,
    sub_index: int,
    slave: str,
    what: str,
    who: str | None = None,
    tries: int = 1,
    on_emergency: Callable[[int, int], None] | None = None,
) -> Any:
    """One SDO transfer (``call``: a pysoem ``sdo_read``/``sdo_write``) with pysoem's errors as ours.

    An abort raises :class:`SdoAbortError` at once (its code, ``index``, ``sub_index``,
    ``slave``). No answer is tried ``tries`` times in all - SDO transfers are
    idempotent - then raised as :class:`BusTimeoutError`. An emergency that
    arrives in the mailbox instead of the answer goes to ``on_emergency(error
    code, error register)`` and counts as a try without answer. ``what``: "read"
    or "write"; ``who``: the slave as the timeout's message names it (default ``slave``).
    """
    last = ""
    for _ in range(tries):
        try:
            return call()
        except pysoem.SdoError as exc:
            raise SdoAbortError(exc.abort_code, index=index, sub_index=sub_index, slave=slave) from None
        except pysoem.Emergency as exc:
            if on_emergency is not None:
                on_emergency(int(exc.error_code), int(exc.error_reg))
            last = f"emergency 0x{exc.error_code:04X}"
        except NO_ANSWER as exc:
            last = f"{type(exc).__name__}: {getattr(exc, 'message', None) or exc}"
    raise BusTimeoutError(
        f"{who or slave}: no answer to SDO {what} 0x{index:04X}:{sub_index:02X} "
        f"after {tries} {'try' if tries == 1 else 'tries'} ({last})"
    )


def read_register(slave: Any, ado: int, size: int, timeout_us: int | None = None) -> bytes | None:
    """``size`` bytes of a slave's registers at ``ado`` (one FPRD at its station address); None: no answer."""
    try:
        data = slave._fprd(ado, size) if timeout_us is None else slave._fprd(ado, size, timeout_us)
    except NO_FRAME_ANSWER:
        return None
    return bytes(data)


def write_register(slave: Any, ado: int, data: bytes, timeout_us: int) -> bool:
    """``data`` into a slave's registers at ``ado`` (one FPWR); False: no answer."""
    try:
        slave._fpwr(ado, data, timeout_us)
    except NO_FRAME_ANSWER:
        return False
    return True


SOEM_ERROR_LIST = 64  # EC_MAXELIST: SOEM's error queue holds at most this many


def object_dictionary(slave: Any, indices: Collection[int] | None = None) -> Iterator[tuple[Any, list[Any]]]:
    """(object, its entries) of ``slave``'s object dictionary by SDO Information (pysoem's ``slave.od``; each
    object's entries are read when reached), only objects in ``indices`` when given.

    A failed SDO Information exchange raises FieldbusError ("SDO Information: ...")
    where it happens, after the objects already yielded. At the end, failed or not,
    SOEM's error queue is emptied (:func:`drop_queued_errors`).
    """
    try:
        for obj in slave.od:
            if indices is None or obj.index in indices:
                yield obj, list(obj.entries)
    except Exception as exc:  # pysoem raises SdoInfoError, or a bare Exception for a queued error
        raise FieldbusError(f"SDO Information: {getattr(exc, 'message', None) or exc}") from None
    finally:
        drop_queued_errors(slave)


def drop_queued_errors(slave: Any) -> None:
    """Empty SOEM's error queue after reading SDO Information.

    SOEM asks for every sub-index up to an object's highest; a device with gaps in an object
    (0x6000:11 without 0x6000:01) answers an SDO Information error for each, which SOEM queues
    and pysoem's ``od`` leaves there. The next SDO call on *another* slave would pop it and fail
    pysoem's assertion that the error is its own. ``mbx_receive`` pops one queued error a call.
    """
    for _ in range(SOEM_ERROR_LIST + 1):
        try:
            slave.mbx_receive()
            return
        except Exception:  # an error popped (pysoem raises a bare Exception for SDO Information errors)
            continue


class _FrameBudget(Protocol):
    frame_timeout_us: int
    _frame_sent: bool


class SoemPort:
    """Slave registers through pysoem's ``_fprd`` / ``_fpwr``: one frame each, waiting the owner's frame
    timeout (below SOEM's EC_TIMEOUTRET, so SOEM sends it once); marks the cycle's datagram as spent."""

    def __init__(self, owner: _FrameBudget, slave: Any) -> None:
        self.owner = owner
        self.slave = slave

    def read(self, ado: int, size: int) -> bytes | None:
        self.owner._frame_sent = True
        return read_register(self.slave, ado, size, self.owner.frame_timeout_us)

    def write(self, ado: int, data: bytes) -> bool:
        self.owner._frame_sent = True
        return write_register(self.slave, ado, data, self.owner.frame_timeout_us)


def request_state(master: Any, state: int) -> None:
    """Request ``state`` (an AL state code) of every slave at once (SOEM's ``write_state``)."""
    master.state = state
    master.write_state()


def check_state(master: Any, state: int, timeout_us: int) -> int:
    """Wait at most ``timeout_us`` for every slave to show ``state``; the lowest state they show
    (SOEM's ``state_check``)."""
    return int(master.state_check(state, timeout_us))


def _eeprom_not_loaded(slave: Any) -> str:
    """A slave left in INIT whose ESC did not load its EEPROM (0x0502 bits 11/12: a wrong checksum of the
    configuration area leaves the PDI off, so its application never answers): the reason, else ""."""
    if slave.state & 0x0F != 0x01:
        return ""
    raw = read_register(slave, 0x0502, 2, 2000)
    if raw is None or not int.from_bytes(raw, "little") & 0x1800:
        return ""
    return (
        "; its ESC did not load the EEPROM (checksum error in the configuration area): "
        "fieldbus eeprom write/alias repairs it (docs/eeprom.md)"
    )


def state_error(
    master: Any, slaves: Sequence[Any], names: Sequence[str], target: str, lowest: int, where: str = ""
) -> StateTransitionError:
    """Why not every slave reached ``target`` ("PRE-OP", "SAFE-OP", "OP"): each slave's state and AL status
    code, read now (``read_state``), as a :class:`~fieldbus.errors.StateTransitionError` to raise."""
    master.read_state()
    want = STATE_CODES[target]
    lines = []
    first_code: int | None = None
    for i, s in enumerate(slaves):
        if (s.state & 0x0F) != want or s.state & AL_ERROR:
            code = s.al_status
            first_code = code if first_code is None else first_code
            lines.append(
                f"  position {i} ({names[i] if i < len(names) else '?'}): "
                f"{state_name(s.state)}, AL status code 0x{code:04X} {al_status_name(code)}"
                + _eeprom_not_loaded(s)
            )
    return StateTransitionError(
        f"{where}not all slaves reached {target} (lowest {state_name(lowest)}):\n" + "\n".join(lines),
        al_status=first_code,
    )
