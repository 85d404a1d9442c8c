"""Classic BPF socket filters (``SO_ATTACH_FILTER``): drop datagrams in the kernel, before a read.

A program is a sequence of ``(code, jt, jf, k)`` instructions (``linux/filter.h``).
Loads (``ld [k]``, ``ldh [k]``) read big-endian from the packet as the socket's
protocol sees it: the Ethernet header for a packet socket, the UDP header for a
UDP socket (payload at offset 8). The program's return value is how many bytes
to keep; 0 drops the packet, and an out-of-range load drops it too.
"""

from __future__ import annotations

import ctypes
import socket
import struct
from collections.abc import Sequence

SO_ATTACH_FILTER = 26
UDP_HEADER = 8  # bytes before a UDP socket filter's payload
LD_W_ABS, LDH_ABS, JEQ_K, RET_K = 0x20, 0x28, 0x15, 0x06  # ld [k] (32 bit), ldh [k], jeq #k, ret #k
ACCEPT, DROP = 0xFFFFFFFF, 0
_INSN = struct.Struct("HBBI")

Instruction = tuple[int, int, int, int]


def attach_filter(sock: socket.socket, program: Sequence[Instruction]) -> None:
    """Attach ``program`` to ``sock`` (the kernel copies it); raises OSError when refused."""
    code = ctypes.create_string_buffer(b"".join(_INSN.pack(*i) for i in program))
    prog = struct.pack("HL", len(program), ctypes.addressof(code))  # struct sock_fprog: count, pointer
    sock.setsockopt(socket.SOL_SOCKET, SO_ATTACH_FILTER, prog)


def drop_udp_payload_u64(offset: int, value: bytes) -> list[Instruction]:
    """A UDP socket program dropping datagrams whose payload has the 8 bytes ``value`` at ``offset``."""
    if len(value) != 8:
        raise ValueError(f"drop_udp_payload_u64: 8 bytes expected, got {len(value)}")
    hi, lo = struct.unpack(">II", value)  # the words as ld [k] reads them
    at = UDP_HEADER + offset
    return [
        (LD_W_ABS, 0, 0, at),
        (JEQ_K, 0, 2, hi),  # first word differs: keep
        (LD_W_ABS, 0, 0, at + 4),
        (JEQ_K, 1, 0, lo),  # both equal: drop
        (RET_K, 0, 0, ACCEPT),
        (RET_K, 0, 0, DROP),
    ]
