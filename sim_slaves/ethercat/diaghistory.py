"""The emulated device's diagnosis history, object 0x10F3 of ETG.1020.

Sub 1 the maximum number of messages, sub 2 the sub-index of the newest
(0: none yet), sub 3 the newest acknowledged (written by the master), sub 4
new messages available, sub 5 flags, subs 6..5+max the messages in a ring
(see :mod:`fieldbus.diagnosis` for the message layout). A CiA 402 drive that
faults writes one message: diag code 0xE800 with the error code 0x603F in
its high word (ETG.1020: "emergency error code as defined in DS301 / DS4xx"),
severity error, a local time stamp [ns], and two parameters: the error code
(UINT16) and the axis (UINT8, 1-based).
"""

from __future__ import annotations

from fieldbus.core import datatypes
from fieldbus.core.diagnosis import (
    DIAG_FIRST_MESSAGE,
    DIAG_FLAGS,
    DIAG_HISTORY,
    DIAG_MAX_MESSAGES,
    DIAG_NEW_AVAILABLE,
    DIAG_NEWEST,
    DIAG_NEWEST_ACK,
    emcy_diag_code,
    encode_diag_message,
)
from sim_slaves.od import Access, ObjectCode, ObjectDictionary

MAX_MESSAGES = 16  # messages the emulated device keeps (the oldest is overwritten)
UINT8, UINT16 = 0x0005, 0x0006  # CoE data types of the message parameters


def _type(name: str) -> datatypes.DataType:
    dt = datatypes.lookup(name)
    assert dt is not None
    return dt


def add_diag_history(od: ObjectDictionary, max_messages: int = MAX_MESSAGES) -> None:
    """Give ``od`` an empty diagnosis history 0x10F3 of ``max_messages`` messages."""
    u8, u16, boolean = _type("uint8"), _type("uint16"), _type("bool")
    od.describe(DIAG_HISTORY, "Diagnosis history", ObjectCode.RECORD)
    od.add(
        DIAG_HISTORY, 0, u8, DIAG_FIRST_MESSAGE + max_messages - 1, access=Access.RO, name="Highest sub-index"
    )
    od.add(DIAG_HISTORY, DIAG_MAX_MESSAGES, u8, max_messages, access=Access.RO, name="Maximum Messages")
    od.add(DIAG_HISTORY, DIAG_NEWEST, u8, 0, access=Access.RO, name="Newest Message")
    od.add(DIAG_HISTORY, DIAG_NEWEST_ACK, u8, 0, name="Newest Acknowledged Message")
    od.add(DIAG_HISTORY, DIAG_NEW_AVAILABLE, boolean, 0, access=Access.RO, name="New Messages Available")
    od.add(DIAG_HISTORY, DIAG_FLAGS, u16, 0, name="Flags")
    for k in range(max_messages):
        od.add(
            DIAG_HISTORY,
            DIAG_FIRST_MESSAGE + k,
            None,
            b"",
            access=Access.RO,
            name=f"Diagnosis Message {k + 1:03d}",
        )


def record_fault(od: ObjectDictionary, error_code: int, timestamp_ns: int, axis: int = 0) -> bool:
    """A drive fault ``error_code`` (0x603F) of ``axis`` (0-based) into ``od``'s history; False: it has none."""
    if not od.has(DIAG_HISTORY, DIAG_MAX_MESSAGES):
        return False
    size = int(od.get_value(DIAG_HISTORY, DIAG_MAX_MESSAGES))
    newest = int(od.get_value(DIAG_HISTORY, DIAG_NEWEST))
    sub = (
        DIAG_FIRST_MESSAGE
        if newest < DIAG_FIRST_MESSAGE or newest >= DIAG_FIRST_MESSAGE + size - 1
        else newest + 1
    )
    message = encode_diag_message(
        emcy_diag_code(error_code), timestamp_ns, ((UINT16, error_code), (UINT8, axis + 1))
    )
    od.entry(DIAG_HISTORY, sub).value = message
    od.set_value(DIAG_HISTORY, DIAG_NEWEST, sub)
    od.set_value(DIAG_HISTORY, DIAG_NEW_AVAILABLE, 1)
    return True
