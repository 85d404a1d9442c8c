"""Firmware images the emulated EtherCAT drives take over FoE: a small header, then the payload.

    from fieldbus.testing import firmware_image
    image = firmware_image(revision=0x0002_0000, size=40_000)

Layout (little-endian): ``b"FBFW"``, u32 revision, u32 payload length, u32
CRC-32 of the payload, then the payload. An emulated drive takes a file
whose name ends in ``.efw`` in BOOTSTRAP only, checks the header and CRC
when the last packet arrives (else FoE error 0x800B, program error), and
reports the image's revision (0x1018:03 and the SII) after its next power
cycle. Real devices have their own formats; this one only lets tests see
that a complete, intact image arrived.
"""

from __future__ import annotations

import random
import struct
import zlib

from fieldbus.errors import FieldbusError

MAGIC = b"FBFW"
_HEAD = struct.Struct("<4sIII")


def firmware_image(revision: int, size: int = 4096, *, seed: int = 0) -> bytes:
    """An image for the emulated drives with ``revision`` (u32) and ``size`` bytes of payload."""
    if not 0 <= revision <= 0xFFFFFFFF or size < 0:
        raise FieldbusError(f"firmware image: revision {revision} (u32) and size {size} (>= 0)")
    payload = random.Random(seed).randbytes(size)
    return _HEAD.pack(MAGIC, revision, size, zlib.crc32(payload)) + payload


def image_revision(image: bytes) -> int | None:
    """The revision of an intact image (header and CRC right), else None."""
    if len(image) < _HEAD.size:
        return None
    magic, revision, size, crc = _HEAD.unpack_from(image)
    payload = image[_HEAD.size :]
    if magic != MAGIC or size != len(payload) or zlib.crc32(payload) != crc:
        return None
    return int(revision)
