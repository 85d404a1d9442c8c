"""A CiA 301 SDO client over a python-can bus (expedited and segmented transfers).

Used for bring-up (identity, SDO plans) and recovery; never in the cycle's hot
path. Frames for other COB-IDs seen while waiting go to ``on_other`` so a
caller can keep heartbeats and EMCYs.
"""

from __future__ import annotations

import struct
import time
from collections.abc import Callable
from typing import Any

from fieldbus.errors import BusTimeoutError, SdoAbortError

RSDO, TSDO = 0x600, 0x580
ABORT_TIMEOUT = 0x05040000  # SDO protocol timed out
ABORT_COMMAND = 0x05040001  # client/server command specifier not valid


class SdoClient:
    """SDO client for nodes on ``bus`` (python-can). ``timeout_s``: per request/response."""

    def __init__(
        self, bus: Any, *, timeout_s: float = 0.5, on_other: Callable[[Any], None] | None = None
    ) -> None:
        import can

        self._can = can
        self.bus = bus
        self.timeout_s = timeout_s
        self.on_other = on_other
        self.transfers = 0

    def _request(self, node: int, payload: bytes, index: int, sub: int) -> bytes:
        self.bus.send(self._can.Message(arbitration_id=RSDO + node, data=payload, is_extended_id=False))
        deadline = time.monotonic() + self.timeout_s
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise BusTimeoutError(
                    f"node {node}: no SDO answer for 0x{index:04X}:{sub:02X} within {self.timeout_s * 1e3:.0f} ms"
                )
            msg = self.bus.recv(timeout=remaining)
            if msg is None:
                continue
            if msg.arbitration_id != TSDO + node or msg.is_extended_id or len(msg.data) != 8:
                if self.on_other is not None:
                    self.on_other(msg)
                continue
            data = bytes(msg.data)
            if data[0] == 0x80:
                code = struct.unpack_from("<I", data, 4)[0]
                raise SdoAbortError(code, index=index, subindex=sub)
            self.transfers += 1
            return data

    def upload(self, node: int, index: int, sub: int) -> bytes:
        """Read ``index:sub`` of ``node``."""
        resp = self._request(node, struct.pack("<BHB4x", 0x40, index, sub), index, sub)
        cmd = resp[0]
        if cmd >> 5 != 2:
            raise SdoAbortError(ABORT_COMMAND, index=index, subindex=sub, detail=f"answer 0x{cmd:02X}")
        if cmd & 0x02:  # expedited
            n = 4 - ((cmd >> 2) & 0x03) if cmd & 0x01 else 4
            return resp[4 : 4 + n]
        size = struct.unpack_from("<I", resp, 4)[0] if cmd & 0x01 else None
        out = bytearray()
        toggle = 0
        while True:
            seg = self._request(node, bytes([0x60 | toggle]) + bytes(7), index, sub)
            if seg[0] >> 5 != 0 or seg[0] & 0x10 != toggle:
                raise SdoAbortError(0x05030000, index=index, subindex=sub, detail="toggle bit")
            out += seg[1 : 8 - ((seg[0] >> 1) & 0x07)]
            toggle ^= 0x10
            if seg[0] & 0x01:
                return bytes(out if size is None else out[:size])

    def download(self, node: int, index: int, sub: int, data: bytes) -> None:
        """Write ``data`` to ``index:sub`` of ``node``."""
        if len(data) <= 4:
            cmd = 0x23 | (4 - len(data)) << 2
            self._request(node, struct.pack("<BHB", cmd, index, sub) + data.ljust(4, b"\0"), index, sub)
            return
        self._request(node, struct.pack("<BHBI", 0x21, index, sub, len(data)), index, sub)
        toggle = 0
        for pos in range(0, len(data), 7):
            chunk = data[pos : pos + 7]
            last = pos + 7 >= len(data)
            cmd = toggle | (7 - len(chunk)) << 1 | (0x01 if last else 0)
            resp = self._request(node, bytes([cmd]) + chunk.ljust(7, b"\0"), index, sub)
            if resp[0] & 0x10 != toggle:
                raise SdoAbortError(0x05030000, index=index, subindex=sub, detail="toggle bit")
            toggle ^= 0x10
