"""SII images (fieldbus.core.sii) and the EEPROM interface (fieldbus.wire.eeprom) against the emulated ESC.

The emulated ESC is ours, so these tests check our master against our own
emulator; the oracle tests (pysoem's own eeprom_read/eeprom_write over veth)
are in tests/integration/test_eeprom_veth.py.
"""

from __future__ import annotations

import pytest

from fieldbus.commands.demo import DEMO_MAP
from fieldbus.core import sii
from fieldbus.core.pdo import load_drive_map
from fieldbus.wire.eeprom import ST_CHECKSUM, ST_NOT_LOADED, EepromError, EepromPort
from sim_slaves.ethercat import EscChain
from sim_slaves.ethercat.sii import build_sii


def _chain(n: int = 2) -> EscChain:
    return EscChain.from_maps([load_drive_map(DEMO_MAP)] * n)


def _port(chain: EscChain, i: int) -> EepromPort:
    esc = chain.slaves[i]
    return EepromPort(lambda a, n: esc.read(a, n, 0), lambda a, d: esc.write(a, d, 0), who=f"slave {i}")


def test_crc8_matches_a_known_configuration_area() -> None:
    # bytes 0-13 all zero: the CRC (poly 0x07, init 0xFF) computed by hand from the definition
    crc = 0xFF
    for _ in range(14):
        for _ in range(8):
            crc = ((crc << 1) ^ 0x07) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    assert sii.crc8(bytes(14)) == crc
    assert sii.crc8(b"") == 0xFF
    # one bit flipped anywhere in the area changes the checksum
    base = bytes(range(14))
    assert all(sii.crc8(base[:k] + bytes([base[k] ^ 1]) + base[k + 1 :]) != sii.crc8(base) for k in range(14))


def test_decode_names_identity_strings_sms_and_pdos() -> None:
    drive = load_drive_map(DEMO_MAP)
    image = bytes(build_sii(drive, alias=7).data)
    c = sii.decode(image)
    assert (c.vendor_id, c.product_code) == (drive.vendor_id, drive.product_id)
    assert c.alias == 7 and c.checksum_ok
    assert c.general is not None and c.general.name == drive.name
    assert [sm.type for sm in c.sync_managers] == ["mailbox out", "mailbox in", "outputs", "inputs"]
    assert [p.index for p in c.rx_pdos] == [p.index for p in drive.rpdo]
    assert [e.index for e in c.tx_pdos[0].entries] == [ch.index for ch in drive.tpdo[0].channels]
    assert "CoE" in c.mailbox_protocols
    assert "identity" in sii.format_text(c)


def test_alias_changes_the_checksum_and_a_bad_image_is_a_typed_error() -> None:
    image = bytes(build_sii(load_drive_map(DEMO_MAP)).data)
    new = sii.with_alias(image, 0x1234)
    assert sii.decode(new).alias == 0x1234 and sii.checksum_ok(new)
    assert new[14] != image[14]
    with pytest.raises(sii.SiiFormatError, match="even number"):
        sii.decode(image[:-1])
    broken = bytearray(image)
    broken[0x80:0x84] = b"\x0a\x00\xff\x7f"  # strings category claiming 32767 words
    with pytest.raises(sii.SiiFormatError, match="word 0x0040"):
        sii.decode(bytes(broken))
    with pytest.raises(sii.SiiIdentityError, match="--force"):
        sii.check_identity(image, 1, 2)
    sii.check_identity(image, 1, 2, force=True)


def test_read_image_through_the_registers_equals_the_emulated_eeprom() -> None:
    chain = _chain()
    port = _port(chain, 1)
    image = port.read_image()
    want = bytes(chain.slaves[1].sii.data)
    assert image == want[: len(image)]
    assert sii.image_end(want) <= len(image)


def test_alias_written_through_the_registers_is_loaded_at_the_next_power_up_only() -> None:
    chain = _chain()
    port = _port(chain, 0)
    image = port.read_image()
    new = sii.with_alias(image, 0x0BEE)
    assert port.write_image(new, old=image) == 2  # word 4 and the checksum word
    assert chain.slaves[0].alias == 0  # the ESC loads 0x0012 at power-up, not at a write
    chain.power_cycle(0)
    assert chain.slaves[0].alias == 0x0BEE
    assert port.status() & (ST_CHECKSUM | ST_NOT_LOADED) == 0
    assert sii.decode(port.read_image()).alias == 0x0BEE


def test_a_wrong_checksum_is_reported_as_the_esc_does_after_power_up() -> None:
    chain = _chain()
    port = _port(chain, 1)
    image = port.read_image()
    bad = bytearray(sii.with_alias(image, 5))
    bad[14] ^= 0xFF  # checksum wrong
    port.write_word(4, 5)
    port.write_word(7, int.from_bytes(bad[14:16], "little"))
    chain.power_cycle(1)
    esc = chain.slaves[1]
    st = port.status()
    assert st & ST_CHECKSUM and st & ST_NOT_LOADED
    assert int.from_bytes(esc.read(0x0110, 2, 0), "little") & 0x0001 == 0  # PDI not operational
    assert esc.alias == 0  # the area was not loaded
    esc.write(0x0120, b"\x02\x00", 0)  # PRE-OP requested: nobody answers, INIT stays
    assert esc.read(0x0130, 1, 0) == b"\x01"
    # repaired: checksum recomputed, loaded at the next power-up
    port.write_word(7, int.from_bytes(sii.with_checksum(bytes(bad))[14:16], "little"))
    chain.power_cycle(1)
    assert port.status() & (ST_CHECKSUM | ST_NOT_LOADED) == 0 and esc.alias == 5


def test_a_write_without_enable_sets_error_bit_14_and_nop_clears_it() -> None:
    chain = _chain(1)
    esc = chain.slaves[0]
    esc.write(0x0508, b"\x34\x12", 0)
    esc.write(0x0502, b"\x00\x02\x10\x00\x00\x00", 0)  # write command, no enable bit
    st = int.from_bytes(esc.read(0x0502, 2, 0), "little")
    assert st & 0x4000 and chain.slaves[0].sii.word(0x10) != 0x1234
    esc.write(0x0502, b"\x00\x00", 0)
    assert int.from_bytes(esc.read(0x0502, 2, 0), "little") & 0x4000 == 0


def test_a_write_past_the_eeprom_end_is_refused() -> None:
    chain = _chain(1)
    port = _port(chain, 0)
    with pytest.raises(EepromError, match="not acknowledged"):
        port.write_word(0x7FFF, 1)


def test_a_write_keeps_the_interface_busy_for_some_status_reads() -> None:
    chain = _chain(1)
    port = _port(chain, 0)
    before = port.datagrams
    port.write_word(0x10, port.read_words(0x10, 1)[0] | port.read_words(0x10, 1)[1] << 8)
    # wait, clear?, data, command, busy polls (2 busy + 1 idle), read-back (wait, command, wait, data)
    assert port.datagrams - before >= 7


def test_decode_of_random_bytes_is_a_result_or_a_typed_error() -> None:
    import random

    rng = random.Random(7)
    base = bytes(build_sii(load_drive_map(DEMO_MAP)).data)
    decoded = 0
    for k in range(400):
        data = bytearray(base)
        for _ in range(rng.randint(1, 40)):  # flip bytes anywhere, categories included
            data[rng.randrange(len(data))] = rng.randrange(256)
        if k % 5 == 0:
            data = data[: 2 * rng.randrange(0x38, len(data) // 2)]
        try:
            sii.format_text(sii.decode(bytes(data)))
            decoded += 1
        except sii.SiiFormatError as exc:
            assert "word" in str(exc) or "bytes" in str(exc)
    assert decoded > 100


def test_a_damaged_category_length_stops_the_read_at_the_eeprom_size() -> None:
    chain = _chain(1)
    esc = chain.slaves[0]
    esc.sii.write_word(0x41, 0x7FFF)  # the first category claims 32767 words
    port = _port(chain, 0)
    image = port.read_image()
    kbit = esc.sii.word(0x3E) + 1
    assert len(image) <= kbit * 128  # bytes: (Kbit + 1) x 1024 / 8
    assert port.datagrams < 4 * kbit * 128  # bounded: about 4 datagrams per 8 bytes


def _esi_config_data() -> list[tuple[str, bytes]]:
    """Every device's <Eeprom><ConfigData> in the vendor ESI files under tests/data/esi (read here with
    ElementTree: the vendor's own bytes, in EEPROM order)."""
    import xml.etree.ElementTree as ET
    from pathlib import Path

    found: list[tuple[str, bytes]] = []
    for f in sorted((Path(__file__).resolve().parents[1] / "data" / "esi").glob("*.xml")):
        for dev in ET.parse(f).getroot().iter("Device"):
            cfg = dev.find("Eeprom/ConfigData")
            if cfg is not None and cfg.text and cfg.text.strip():
                name = (dev.findtext("Type") or "?").strip()
                found.append((f"{f.name}:{name}", bytes.fromhex(cfg.text.strip())))
    return found


@pytest.mark.parametrize(("device", "config"), _esi_config_data())
def test_an_esi_s_configuration_area_written_through_the_registers_is_the_one_read_after_power_up(
    device: str, config: bytes
) -> None:
    """The vendor's ConfigData (SII words 0 on) into the emulated EEPROM by the register sequence, the
    checksum recomputed: after a power cycle the ESC loads it (no checksum error) and reads it back as
    the vendor wrote it."""
    assert config and len(config) <= 14, device
    chain = _chain(1)
    port = _port(chain, 0)
    image = port.read_image()
    new = sii.with_checksum(config + image[len(config) :])
    assert new[: len(config)] != image[: len(config)]  # the emulator's own area differs: a real write
    assert port.write_image(new, old=image) >= 1
    chain.power_cycle(0)
    assert port.status() & (ST_CHECKSUM | ST_NOT_LOADED) == 0
    back = port.read_image()
    assert back[: len(config)] == config
    assert sii.checksum_ok(back)
