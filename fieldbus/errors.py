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


class SdoAbortError(FieldbusError):
    """A device answered an SDO transfer with an abort code (CiA 301 / ETG.1000.6)."""

    def __init__(
        self,
        code: int,
        *,
        index: int,
        subindex: int,
        slave: str = "",
        detail: str = "",
    ) -> None:
        from fieldbus.core.sdo.abort import abort_name

        self.code = code
        self.name = abort_name(code)
        self.index = index
        self.subindex = subindex
        self.slave = slave
        self.detail = detail
        who = f"{slave}: " if slave else ""
        extra = f" ({detail})" if detail else ""
        super().__init__(f"{who}SDO abort 0x{code:08X} '{self.name}' on 0x{index:04X}:{subindex:02X}{extra}")


class SdoMismatchError(FieldbusError):
    """An SDO read-back did not return what was written."""

    def __init__(
        self, *, index: int, subindex: int, expected: bytes, received: bytes, slave: str = ""
    ) -> None:
        self.index = index
        self.subindex = subindex
        self.expected = expected
        self.received = received
        self.slave = slave
        who = f"{slave}: " if slave else ""
        super().__init__(
            f"{who}read-back of 0x{index:04X}:{subindex:02X} gave {received.hex()} "
            f"instead of {expected.hex()}"
        )


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
