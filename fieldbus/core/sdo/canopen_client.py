"""The CiA 301 SDO client protocol (expedited and segmented transfers), sans-IO.

:func:`sdo_upload` and :func:`sdo_download` are generators: each yields the
8-byte request to send to the node (COB-ID 0x600 + node), is sent the node's
8-byte answer (0x580 + node) and returns the data when the transfer is done.
The CANopen backend drives them blocking at bring-up and one frame per cycle
during recovery; an abort from the node, or an answer that breaks the
protocol, raises :class:`~fieldbus.errors.SdoAbortError` with its code.
"""

from __future__ import annotations

import struct
from collections.abc import Generator

from fieldbus.errors import SdoAbortError

ABORT_TOGGLE = 0x05030000  # toggle bit not alternated
ABORT_TIMEOUT = 0x05040000  # SDO protocol timed out
ABORT_COMMAND = 0x05040001  # client/server command specifier not valid

SdoSteps = Generator[bytes, bytes, bytes]  # yields requests, is sent each response, returns the data


# -- SDO client protocol (CiA 301 7.2.4.3), sans-IO --------------------------------------------
def _check(resp: bytes, index: int, sub: int) -> None:
    if len(resp) != 8:
        raise SdoAbortError(ABORT_COMMAND, index=index, sub_index=sub, detail=f"{len(resp)}-byte answer")
    if resp[0] == 0x80:
        raise SdoAbortError(struct.unpack_from("<I", resp, 4)[0], index=index, sub_index=sub)


def sdo_upload(index: int, sub: int) -> SdoSteps:
    """Read ``index:sub``: yields each request, expects each response sent in; returns the data."""
    resp = yield struct.pack("<BHB4x", 0x40, index, sub)
    _check(resp, index, sub)
    cmd = resp[0]
    if cmd >> 5 != 2 or (resp[1] | resp[2] << 8, resp[3]) != (index, sub):
        raise SdoAbortError(ABORT_COMMAND, index=index, sub_index=sub, detail=f"answer {resp.hex()}")
    if cmd & 0x02:  # expedited
        n = 4 - ((cmd >> 2) & 0x03) if cmd & 0x01 else 4
        return resp[4 : 4 + n]
    size = struct.unpack_from("<I", resp, 4)[0] if cmd & 0x01 else None
    out = bytearray()
    toggle = 0
    while True:
        seg = yield bytes([0x60 | toggle]) + bytes(7)
        _check(seg, index, sub)
        if seg[0] >> 5 != 0:
            raise SdoAbortError(ABORT_COMMAND, index=index, sub_index=sub, detail=f"segment {seg.hex()}")
        if seg[0] & 0x10 != toggle:
            raise SdoAbortError(ABORT_TOGGLE, index=index, sub_index=sub, detail="toggle bit")
        out += seg[1 : 8 - ((seg[0] >> 1) & 0x07)]
        toggle ^= 0x10
        if seg[0] & 0x01:
            return bytes(out if size is None else out[:size])


def sdo_download(index: int, sub: int, data: bytes) -> SdoSteps:
    """Write ``data`` to ``index:sub`` (expedited up to 4 bytes, segmented beyond); returns b''."""
    if len(data) <= 4:
        cmd = 0x23 | (4 - len(data)) << 2
        resp = yield struct.pack("<BHB", cmd, index, sub) + data.ljust(4, b"\0")
        _check(resp, index, sub)
        if resp[0] != 0x60:
            raise SdoAbortError(ABORT_COMMAND, index=index, sub_index=sub, detail=f"answer {resp.hex()}")
        return b""
    resp = yield struct.pack("<BHBI", 0x21, index, sub, len(data))
    _check(resp, index, sub)
    if resp[0] != 0x60:
        raise SdoAbortError(ABORT_COMMAND, index=index, sub_index=sub, detail=f"answer {resp.hex()}")
    toggle = 0
    for pos in range(0, len(data), 7):
        chunk = data[pos : pos + 7]
        last = pos + 7 >= len(data)
        cmd = toggle | (7 - len(chunk)) << 1 | (0x01 if last else 0)
        resp = yield bytes([cmd]) + chunk.ljust(7, b"\0")
        _check(resp, index, sub)
        if resp[0] & 0xEF != 0x20:
            raise SdoAbortError(ABORT_COMMAND, index=index, sub_index=sub, detail=f"answer {resp.hex()}")
        if resp[0] & 0x10 != toggle:
            raise SdoAbortError(ABORT_TOGGLE, index=index, sub_index=sub, detail="toggle bit")
        toggle ^= 0x10
    return b""
