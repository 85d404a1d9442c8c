"""A drive's diagnosis history, read through the running cycle (the public name of :mod:`fieldbus.core.diagnosis`).

``ErrorHistory(op, bus, slave)`` reads CiA 301's pre-defined error field
0x1003, ``DiagnosisHistory(op, bus, slave)`` ETG.1020's diagnosis history
0x10F3; call ``poll()`` once per cycle (after ``exchange()``) until it
returns the entries. The decoding is pure and lives in the core, where the
drive-fault watch (:mod:`fieldbus.core.drivefault`) uses it.
"""

from fieldbus.core.diagnosis import (
    DIAG_EMCY,
    DIAG_HISTORY,
    ERROR_FIELD,
    DiagMessage,
    DiagnosisHistory,
    DiagnosisReader,
    ErrorHistory,
    decode_diag_message,
    emcy_diag_code,
    encode_diag_message,
    error_code,
)

__all__ = [
    "DIAG_EMCY",
    "DIAG_HISTORY",
    "ERROR_FIELD",
    "DiagMessage",
    "DiagnosisHistory",
    "DiagnosisReader",
    "ErrorHistory",
    "decode_diag_message",
    "emcy_diag_code",
    "encode_diag_message",
    "error_code",
]
