"""One error root for the whole library, with structured subclasses.

"You misused it" errors (bad YAML, calling a verb in the wrong phase) are split
from "the device broke protocol" errors (SDO aborts, working-counter misses).
"""

from __future__ import annotations


class FieldbusError(Exception):
    """Root of every error raised by fieldbus."""


class PdoMapError(FieldbusError, ValueError):
    """A drive map or network file is invalid.

    Carries the location: ``file:line:column field.path: message``. Line and
    column are 1-based; either may be ``None`` when the problem has no single
    place in the file (for example a file that cannot be read).
    """

    def __init__(
        self,
        message: str,
        *,
        file: str | None = None,
        line: int | None = None,
        column: int | None = None,
        path: str = "",
    ) -> None:
        self.message = message
        self.file = file
        self.line = line
        self.column = column
        self.path = path
        super().__init__(self.__str__())

    @property
    def location(self) -> str:
        """``file:line:column`` (as much of it as is known)."""
        parts = [self.file or "<string>"]
        if self.line is not None:
            parts.append(str(self.line))
            if self.column is not None:
                parts.append(str(self.column))
        return ":".join(parts)

    def __str__(self) -> str:
        where = self.location
        return f"{where} {self.path}: {self.message}" if self.path else f"{where}: {self.message}"

    def __reduce__(self) -> tuple[object, ...]:  # keep pickling (multiprocessing) working
        return (_rebuild_pdo_map_error, (self.message, self.file, self.line, self.column, self.path))


def _rebuild_pdo_map_error(
    message: str, file: str | None, line: int | None, column: int | None, path: str
) -> PdoMapError:
    return PdoMapError(message, file=file, line=line, column=column, path=path)


# SDO abort codes (CiA 301 table 22; CoE uses the same codes, ETG.1000.6)
ABORT_CODES: dict[int, str] = {
    0x05030000: "Toggle bit not alternated",
    0x05040000: "SDO protocol timed out",
    0x05040001: "Client/server command specifier not valid or unknown",
    0x05040002: "Invalid block size",
    0x05040003: "Invalid sequence number",
    0x05040004: "CRC error",
    0x05040005: "Out of memory",
    0x06010000: "Unsupported access to an object",
    0x06010001: "Attempt to read a write only object",
    0x06010002: "Attempt to write a read only object",
    0x06010003: "Subindex cannot be written, SI0 must be 0 for write access",
    0x06010004: "SDO Complete access not supported for objects of variable length",
    0x06010005: "Object length exceeds mailbox size",
    0x06010006: "Object mapped to RxPDO, SDO download blocked",
    0x06020000: "Object does not exist in the object dictionary",
    0x06040041: "Object cannot be mapped to the PDO",
    0x06040042: "The number and length of the objects to be mapped would exceed PDO length",
    0x06040043: "General parameter incompatibility reason",
    0x06040047: "General internal incompatibility in the device",
    0x06060000: "Access failed due to a hardware error",
    0x06070010: "Data type does not match, length of service parameter does not match",
    0x06070012: "Data type does not match, length of service parameter too high",
    0x06070013: "Data type does not match, length of service parameter too low",
    0x06090011: "Sub-index does not exist",
    0x06090030: "Value range of parameter exceeded (only for write access)",
    0x06090031: "Value of parameter written too high",
    0x06090032: "Value of parameter written too low",
    0x06090036: "Maximum value is less than minimum value",
    0x060A0023: "Resource not available: SDO connection",
    0x08000000: "General error",
    0x08000020: "Data cannot be transferred or stored to the application",
    0x08000021: "Data cannot be transferred or stored to the application because of local control",
    0x08000022: "Data cannot be transferred or stored to the application because of the present device state",
    0x08000023: "Object dictionary dynamic generation fails or no object dictionary is present",
    0x08000024: "No data available",
}


def abort_name(code: int) -> str:
    """Human name of an SDO abort code (``unknown abort code`` if not in the table)."""
    return ABORT_CODES.get(code, "unknown abort code")


class SdoAbortError(FieldbusError):
    """A device answered an SDO transfer with an abort code (CiA 301 / ETG.1000.6)."""

    def __init__(
        self,
        code: int,
        *,
        index: int,
        sub_index: int,
        slave: str = "",
        detail: str = "",
    ) -> None:
        self.code = code
        self.name = abort_name(code)
        self.index = index
        self.sub_index = sub_index
        self.slave = slave
        self.detail = detail
        who = f"{slave}: " if slave else ""
        extra = f" ({detail})" if detail else ""
        super().__init__(f"{who}SDO abort 0x{code:08X} '{self.name}' on 0x{index:04X}:{sub_index:02X}{extra}")


class SdoMismatchError(FieldbusError):
    """An SDO read-back did not return what was written."""

    def __init__(
        self, *, index: int, sub_index: int, expected: bytes, received: bytes, slave: str = ""
    ) -> None:
        self.index = index
        self.sub_index = sub_index
        self.expected = expected
        self.received = received
        self.slave = slave
        who = f"{slave}: " if slave else ""
        super().__init__(
            f"{who}read-back of 0x{index:04X}:{sub_index:02X} gave {received.hex()} "
            f"instead of {expected.hex()}"
        )


class ChannelNameError(FieldbusError, KeyError, ValueError):
    """A process image has no channel of that name (a ``KeyError`` and, as numpy's error was, a ``ValueError``)."""

    def __str__(self) -> str:  # KeyError would show the message in quotes
        return str(self.args[0]) if self.args else ""


class WorkingCounterError(FieldbusError):
    """The working counter of a cycle did not match what the layout expects."""

    def __init__(self, expected: int, received: int, detail: str = "") -> None:
        self.expected = expected
        self.received = received
        extra = f": {detail}" if detail else ""
        super().__init__(f"working counter {received}, expected {expected}{extra}")


class StateTransitionError(FieldbusError):
    """A device did not reach a requested state (EtherCAT AL or CANopen NMT / CiA 402)."""

    def __init__(self, message: str, *, al_status: int | None = None, slave: str = "") -> None:
        self.al_status = al_status
        self.slave = slave
        super().__init__(message)


class BusTimeoutError(FieldbusError, TimeoutError):
    """A bus operation did not complete within its timeout."""


class BackendUnavailableError(FieldbusError, ImportError):
    """A backend's optional dependency is missing; the message says what to install."""


class PhaseError(FieldbusError, RuntimeError):
    """A verb was called in a bring-up phase where it is not allowed."""


class RequestError(FieldbusError, ValueError):
    """A request (an SDO transfer asked for in OP) is malformed: refused at submit, nothing queued."""


class BusIoError(FieldbusError):
    """The bus driver failed to send or receive (a python-can ``CanError``, an ``OSError``).

    ``cause`` is the driver's own exception (also chained as ``__cause__``).
    """

    def __init__(self, message: str, cause: BaseException | None = None) -> None:
        self.cause = cause
        super().__init__(message)


class InterfaceInUseError(FieldbusError):
    """Another master holds the interface (network card or CAN channel); ``pid`` is its process (None: unknown)."""

    def __init__(self, interface: str, pid: int | None, program: str = "") -> None:
        self.interface = interface
        self.pid = pid
        self.program = program
        who = f"PID {pid}" if pid is not None else "another process"
        super().__init__(f"interface '{interface}' is in use by {who}" + (f" ({program})" if program else ""))

    def __reduce__(self) -> tuple[object, ...]:  # keep pickling (multiprocessing) working
        return (type(self), (self.interface, self.pid, self.program))
