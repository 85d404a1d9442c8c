"""CoE SDO Information on the emulated slave, through the product's frame master and the in-process chain.

Get OD List, Get Object Description and Get Entry Description as a master
sees them on the wire (mailbox SM0/SM1, counters, fragments), against what the
drive map put in the object dictionary.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from fieldbus.core.al import AL_PREOP
from fieldbus.core.pdo import load_drive_map
from fieldbus.core.sdo import info
from fieldbus.errors import SdoAbortError
from fieldbus.wire.framemaster import FrameMaster, SlaveInfo
from sim_slaves.ethercat.chain import EscChain
from sim_slaves.od import ObjectDictionary

REPO = Path(__file__).resolve().parents[2]
GENERIC = REPO / "fieldbus" / "pdo_maps" / "generic_cia402.yaml"
IO16 = REPO / "tests" / "data" / "io16.yaml"


def _preop(path: Path, mailbox_size: int | None = None) -> tuple[FrameMaster, SlaveInfo, ObjectDictionary]:
    drive = load_drive_map(path)
    if mailbox_size is not None:
        drive = dataclasses.replace(
            drive, ethercat=dataclasses.replace(drive.ethercat, mailbox_size=mailbox_size)
        )
    chain = EscChain.from_maps([drive], app=None)
    master = FrameMaster(lambda frame: chain.process(frame, 0))
    (slave,) = master.identify(master.scan())
    master.setup_mailbox(slave)
    master.request_state(slave.station, AL_PREOP)
    assert not master.wait_state([slave.station], AL_PREOP)
    return master, slave, chain.slaves[0].od


@pytest.mark.parametrize("mailbox", [128, 32])
def test_od_list_is_every_object_also_in_fragments(mailbox: int) -> None:
    master, slave, od = _preop(GENERIC, mailbox)
    assert master.od_list(slave) == od.indices()
    # 32-byte mailbox: 20 bytes of data per fragment, so the list (2 + 2 x objects) needs several
    assert 2 + 2 * len(od.indices()) > mailbox - 12 or mailbox == 128
    rx = master.od_list(slave, info.ListType.RXPDO)
    tx = master.od_list(slave, info.ListType.TXPDO)
    assert {0x6040, 0x607A, 0x60FF, 0x6071, 0x6060} <= set(rx)
    assert {0x6041, 0x6064, 0x606C, 0x6077, 0x6061} <= set(tx)
    assert 0x6041 not in rx and 0x6040 not in tx and 0x1018 not in rx + tx


def test_fragment_counts_and_flags() -> None:
    frags = info.fragments(info.InfoOpcode.OD_LIST_RES, bytes(range(40)), 16)  # 10 data bytes each
    assert len(frags) == 4
    heads = [info.HEADER.unpack_from(f) for f in frags]
    assert [h[1] for h in heads] == [0x82, 0x82, 0x82, 0x02]
    assert [h[3] for h in heads] == [3, 2, 1, 0]
    joined = info.Reassembly(info.InfoOpcode.OD_LIST_RES)
    assert [joined.add(f) for f in frags][:3] == [None, None, None]
    assert joined.data == bytes(range(40))


def test_object_descriptions_name_type_code() -> None:
    master, slave, _ = _preop(GENERIC)
    cw = master.object_description(slave, 0x6040)
    assert (cw.name, info.type_name(cw.data_type), info.OBJECT_CODES[cw.object_code], cw.max_sub) == (
        "controlword",
        "uint16",
        "VAR",
        0,
    )
    ident = master.object_description(slave, 0x1018)
    assert (ident.name, ident.data_type, ident.object_code, ident.max_sub) == (
        "Identity object",
        0x0023,
        9,
        4,
    )
    assign = master.object_description(slave, 0x1C12)
    assert (assign.name, info.OBJECT_CODES[assign.object_code], info.type_name(assign.data_type)) == (
        "RxPDO assign",
        "ARRAY",
        "uint16",
    )
    name = master.object_description(slave, 0x1008)
    assert (name.name, info.type_name(name.data_type)) == ("Manufacturer device name", "string")
    mapping = master.object_description(slave, 0x1A01)
    assert (mapping.name, mapping.data_type, mapping.object_code) == ("TxPDO mapping 2", 0x0021, 9)


def test_entry_descriptions_type_length_access() -> None:
    master, slave, _ = _preop(GENERIC)
    cw = master.entry_description(slave, 0x6040, 0)
    assert (cw.name, cw.data_type, cw.bit_length) == ("controlword", 0x0006, 16)
    assert cw.access == info.ACCESS_READ | info.ACCESS_WRITE | info.ACCESS_RXPDO
    assert info.access_text(cw.access) == "rw,rxpdo"
    sw = master.entry_description(slave, 0x6041, 0)
    assert info.access_text(sw.access) == "rw,txpdo"
    vendor = master.entry_description(slave, 0x1018, 1)
    assert (vendor.name, vendor.data_type, vendor.bit_length, info.access_text(vendor.access)) == (
        "Vendor ID",
        0x0007,
        32,
        "ro",
    )
    entry = master.entry_description(slave, 0x1600, 1)
    assert info.access_text(entry.access) == "rw(pre-op)"  # mapping objects: written in PRE-OP only
    name = master.entry_description(slave, 0x1008, 0)
    assert (name.data_type, name.bit_length) == (0x0009, 8 * len("generic_cia402"))


def test_sub_index_objects_are_records_named_after_the_channel() -> None:
    master, slave, _ = _preop(IO16)
    obj = master.object_description(slave, 0x7000)
    assert (obj.name, obj.object_code, obj.max_sub) == ("x7000_01", 9, 1)
    e = master.entry_description(slave, 0x7000, 1)
    assert (e.name, e.data_type, info.access_text(e.access)) == ("x7000_01", 0x0006, "rw,rxpdo")


@pytest.mark.parametrize(
    ("index", "sub", "code"),
    [(0x5555, None, 0x06020000), (0x6040, 3, 0x06090011), (0x5555, 0, 0x06020000)],
)
def test_unknown_objects_answer_an_sdo_info_error(index: int, sub: int | None, code: int) -> None:
    master, slave, _ = _preop(GENERIC)
    with pytest.raises(SdoAbortError) as exc:
        if sub is None:
            master.object_description(slave, index)
        else:
            master.entry_description(slave, index, sub)
    assert exc.value.code == code
    assert (exc.value.index, exc.value.sub_index) == (index, sub or 0)
    # the mailbox keeps working afterwards
    assert master.object_description(slave, 0x6041).name == "statusword"
