"""pysoem's own ``slave.od`` (SOEM's SDO Information client) against the emulated slave over veth."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from fieldbus.core.pdo import load_drive_map
from sim_slaves.ethercat.axes import device_od

pysoem = pytest.importorskip("pysoem")

REPO = Path(__file__).resolve().parents[2]
MAXON = REPO / "tests" / "data" / "ethercat_driver_ros2" / "maxon_epos4_50_5.yaml"

pytestmark = [pytest.mark.veth, pytest.mark.timeout(300), pytest.mark.usefixtures("generous_pysoem_timeouts")]


def _text(v: Any) -> str:
    return v.decode() if isinstance(v, bytes) else str(v)


def test_pysoem_od_lists_names_types_and_access(ethercat_emulator: Any, tmp_path: Path) -> None:
    # a 64-byte mailbox holds 26 indices per answer: the list of 38 objects comes in two fragments
    small = tmp_path / "maxon_small_mailbox.yaml"
    small.write_text(MAXON.read_text() + "\nethercat: {mailbox_size: 64}\n")
    emu = ethercat_emulator([small])
    expected = device_od(load_drive_map(small))  # the emulated device's dictionary (0x10F3 included)
    master = pysoem.Master()
    master.open(emu.iface)
    try:
        assert master.config_init() == 1
        od = master.slaves[0].od
        by_index = {obj.index: obj for obj in od}
        assert len(expected.indices()) > (64 - 6 - 6 - 2) // 2
        assert sorted(by_index) == expected.indices()

        cw = by_index[0x6040]
        assert (_text(cw.name), cw.data_type, cw.object_code) == ("control_word", 0x0006, 7)
        assert cw.bit_length == 16
        assert cw.entries == []
        sw = by_index[0x6041]
        assert (_text(sw.name), sw.data_type) == ("status_word", 0x0006)
        pos = by_index[0x6064]
        assert (pos.data_type, pos.bit_length) == (0x0004, 32)

        ident = by_index[0x1018]
        assert (_text(ident.name), ident.object_code, ident.data_type) == ("Identity object", 9, 0x0023)
        entries = ident.entries
        assert [_text(e.name) for e in entries] == [
            "Highest sub-index supported",
            "Vendor ID",
            "Product code",
            "Revision number",
            "Serial number",
        ]
        assert [e.data_type for e in entries] == [0x0005, 0x0007, 0x0007, 0x0007, 0x0007]
        assert [e.bit_length for e in entries] == [8, 32, 32, 32, 32]
        assert all(e.obj_access == 0x07 for e in entries)  # read in every state, never written

        mapping = by_index[0x1A03]
        assert (_text(mapping.name), mapping.object_code, mapping.data_type) == ("TxPDO mapping 4", 9, 0x0021)
        m_entries = mapping.entries
        assert m_entries[1].obj_access == 0x0F  # read always, written in PRE-OP only
        assert m_entries[1].data_type == 0x0007

        # access of VAR objects: pysoem reads it from the entry list, so read the entries first
        cw.entries  # noqa: B018
        assert cw.obj_access == 0x3F | 0x40  # read/write in every state, RxPDO-mappable
        name = by_index[0x1008]
        name.entries  # noqa: B018
        assert (name.data_type, name.obj_access) == (0x0009, 0x07)
    finally:
        master.close()
