"""`fieldbus import esi` on the single-bit, no-mailbox digital I/O shape (tests/data/esi/fieldbus_bit_io.xml).

The file was written for these tests (see tests/data/esi/SOURCE.md for why no vendor file):
two devices without a mailbox whose fixed PDOs each map one BOOL entry, one PDO per channel;
the 16/16 module splits its outputs over two one-byte sync managers, the 8-input module has
its inputs in SM0. Expected values were read from the file by hand.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from fieldbus import load_drive_map
from fieldbus.cli import main
from fieldbus.core.pdo.layout import layout
from fieldbus.interop.esi import import_esi_file, list_devices

BIT_IO = Path(__file__).resolve().parents[1] / "data" / "esi" / "fieldbus_bit_io.xml"


def test_both_devices_are_listed() -> None:
    devices = list_devices(BIT_IO.read_bytes(), str(BIT_IO))
    assert [(d.type, d.product_code, d.revision) for d in devices] == [
        ("BIT-IO 16/16", 0x0B10, 1),
        ("BIT-IN 8", 0x0B08, 1),
    ]


def test_one_bool_per_pdo_without_a_mailbox() -> None:
    d = import_esi_file(str(BIT_IO), device="BIT-IO 16/16").drive
    assert (d.vendor_id, d.product_id, d.revision) == (0x0F00, 0x0B10, 1)
    assert d.ethercat.coe is False  # no mailbox: nothing to write, the PDOs are as the SII says
    assert [p.index for p in d.rpdo] == [0x1600 + k for k in range(16)]
    assert [p.index for p in d.tpdo] == [0x1A00 + k for k in range(16)]
    assert all(p.fixed for p in (*d.rpdo, *d.tpdo))
    rx = [(c.index, c.sub_index, c.type.name, c.bits) for p in d.rpdo for c in p.channels]
    tx = [(c.index, c.sub_index, c.type.name, c.bits) for p in d.tpdo for c in p.channels]
    assert rx == [(0x7000 + 0x10 * k, 1, "bool", 1) for k in range(16)]
    assert tx == [(0x6000 + 0x10 * k, 1, "bool", 1) for k in range(16)]
    assert [c.name for p in d.rpdo for c in p.channels][:2] == ["output_0", "output_1"]
    # 16 one-bit PDOs pack into 2 bytes each way
    lay = layout(d)
    assert (lay.outputs.bits, lay.outputs.size, lay.inputs.size) == (16, 2, 2)
    assert [e.bit_offset for e in lay.outputs.entries] == list(range(16))
    # outputs over two one-byte sync managers at the ESC's digital output bytes, inputs in SM2
    assert [(s.index, s.type, s.start, s.size) for s in d.sm] == [
        (0, "output", 0x0F00, 1),
        (1, "output", 0x0F01, 1),
        (2, "input", 0x1000, 2),
    ]


def test_an_input_only_module_with_its_inputs_in_sm0() -> None:
    d = import_esi_file(str(BIT_IO), device="0x0B08").drive
    assert d.rpdo == () and [p.index for p in d.tpdo] == [0x1A00 + k for k in range(8)]
    assert [(s.index, s.type, s.size) for s in d.sm] == [(0, "input", 1)]


@pytest.mark.parametrize("device", ["BIT-IO 16/16", "BIT-IN 8"])
def test_the_cli_writes_maps_that_validate(device: str, tmp_path: Path) -> None:
    out = tmp_path / "io.yaml"
    assert main(["import", "esi", str(BIT_IO), "--device", device, "-o", str(out)]) == 0
    assert main(["validate", str(out)]) == 0
    assert load_drive_map(out).ethercat.coe is False
