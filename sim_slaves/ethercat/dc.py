"""Distributed-clock registers of one emulated ESC: a simple, drift-free clock.

Kept in one small class so a faithful model (``fieldbus.core.dc``) can be
swapped in. Times in ns; "now" is the caller's monotonic time, passed in.

Registers (ESC memory, little-endian): 0x0900/0x0904/0x0908/0x090C receive
times of ports 0-3 (u32, latched by a write to 0x0900), 0x0910 system time
(u64: local time + offset), 0x0918 receive time of the processing unit (u64,
latched with 0x0900), 0x0920 system time offset (u64, written by the master),
0x0928 system time delay (u32), 0x0980/0x0981 cyclic unit control/activation,
0x0990 SYNC0 start time, 0x09A0 SYNC0 cycle time: plain memory.
"""

from __future__ import annotations

import struct

HOP_NS = 100  # emulated link + forwarding delay between neighbouring slaves, one way
PROCESS_NS = 400  # emulated delay through one slave's processing unit

_U64 = struct.Struct("<Q")
_U32 = struct.Struct("<I")


class DcClock:
    """Local time = ``now_ns`` (plus this slave's wire position); system time = local + offset."""

    def __init__(self, position: int, chain_length: int) -> None:
        self.position = position
        self.chain_length = chain_length

    def local_time(self, now_ns: int) -> int:
        """The slave's local clock when a frame sent by the master at ``now_ns`` reaches it."""
        return now_ns + self.position * (HOP_NS + PROCESS_NS)

    def latch(self, mem: bytearray, now_ns: int) -> None:
        """A write to 0x0900 passed: store the port receive times and 0x0918."""
        t0 = self.local_time(now_ns)
        downstream = self.chain_length - 1 - self.position
        t1 = t0 + PROCESS_NS + downstream * 2 * (HOP_NS + PROCESS_NS) if downstream else 0
        _U32.pack_into(mem, 0x0900, t0 & 0xFFFFFFFF)
        _U32.pack_into(mem, 0x0904, t1 & 0xFFFFFFFF)
        _U32.pack_into(mem, 0x0908, 0)
        _U32.pack_into(mem, 0x090C, 0)
        _U64.pack_into(mem, 0x0918, t0 & 0xFFFFFFFFFFFFFFFF)

    def system_time(self, mem: bytearray, now_ns: int) -> int:
        offset: int = _U64.unpack_from(mem, 0x0920)[0]
        return (self.local_time(now_ns) + offset) & 0xFFFFFFFFFFFFFFFF

    def fill_system_time(self, mem: bytearray, now_ns: int) -> None:
        """Before a read of 0x0910: put the current system time there."""
        _U64.pack_into(mem, 0x0910, self.system_time(mem, now_ns))
