"""Sans-IO ESC chain: hand-written golden frames per command with their WKC, AL states, SII, CoE, faults."""

from __future__ import annotations

import struct
from pathlib import Path

import pytest

from fieldbus.core.ecat import Command, Datagram, build_master_frame, decode_frame
from fieldbus.core.pdo.load import drive_map_from_text, load_drive_map
from fieldbus.core.pdo.model import DriveMap
from fieldbus.errors import SdoAbortError
from sim_slaves.ethercat import AlState, EscChain, LoopbackApp, build_sii
from sim_slaves.ethercat.bringup import STATION_BASE, bring_up, exchange
from sim_slaves.ethercat.sii import SiiImage
from sim_slaves.od import CommState, ObjectDictionary

MAXON = Path(__file__).resolve().parents[1] / "data" / "ethercat_driver_ros2" / "maxon_epos4_50_5.yaml"
IO16 = (Path(__file__).resolve().parents[1] / "data" / "io16.yaml").read_text()


def hx(text: str) -> bytes:
    return bytes.fromhex(text.replace("|", " "))


REQ = "ff ff ff ff ff ff | 01 01 01 01 01 01 | 88 a4"
REP = "ff ff ff ff ff ff | 03 01 01 01 01 01 | 88 a4"


def io16() -> DriveMap:
    return drive_map_from_text(IO16)


def loopback(drive: DriveMap, od: ObjectDictionary) -> LoopbackApp:
    return LoopbackApp([((0x7000, 1), (0x6000, 1))])


def chain3() -> EscChain:
    return EscChain.from_maps([io16()] * 3, app=loopback)


def addressed(chain: EscChain) -> EscChain:
    """Station addresses 0x1001..0x1003 (as SOEM gives them)."""
    for i in range(len(chain)):
        exchange(
            chain,
            [Datagram.physical(Command.APWR, -i & 0xFFFF, 0x0010, struct.pack("<H", STATION_BASE + i))],
            0,
        )
    return chain


# -- golden frames: request and reply written out by hand --


def test_brd_counts_and_ors_slaves() -> None:
    req = hx(f"{REQ} | 0e 10 | 07 01 00 00 00 00 02 00 00 00 | 00 00 | 00 00")
    # type 0x11 / revision 0x02 OR-ed over 3 slaves, ADP incremented by each, WKC 3
    rep = hx(f"{REP} | 0e 10 | 07 01 03 00 00 00 02 00 00 00 | 11 02 | 03 00")
    assert chain3().process(req, 0) == rep


def test_bwr_and_aprd_apwr_auto_increment() -> None:
    c = chain3()
    bwr = hx(f"{REQ} | 0d 10 | 08 02 00 00 03 01 01 00 00 00 | 00 | 00 00")
    assert c.process(bwr, 0) == hx(f"{REP} | 0d 10 | 08 02 03 00 03 01 01 00 00 00 | 00 | 03 00")
    # APWR to position 1 (ADP = -1): station address 0x1002
    apwr = hx(f"{REQ} | 0e 10 | 02 03 ff ff 10 00 02 00 00 00 | 02 10 | 00 00")
    assert c.process(apwr, 0) == hx(f"{REP} | 0e 10 | 02 03 02 00 10 00 02 00 00 00 | 02 10 | 01 00")
    aprd = hx(f"{REQ} | 0e 10 | 01 04 ff ff 10 00 02 00 00 00 | 00 00 | 00 00")
    assert c.process(aprd, 0) == hx(f"{REP} | 0e 10 | 01 04 02 00 10 00 02 00 00 00 | 02 10 | 01 00")
    # a position past the end addresses nobody: WKC 0
    nobody = hx(f"{REQ} | 0e 10 | 01 05 fd ff 10 00 02 00 00 00 | 00 00 | 00 00")
    assert c.process(nobody, 0) == hx(f"{REP} | 0e 10 | 01 05 00 00 10 00 02 00 00 00 | 00 00 | 00 00")


def test_fprd_fpwr_fprw() -> None:
    c = addressed(chain3())
    fpwr = hx(f"{REQ} | 0e 10 | 05 06 02 10 00 15 02 00 00 00 | 01 02 | 00 00")
    assert c.process(fpwr, 0) == hx(f"{REP} | 0e 10 | 05 06 02 10 00 15 02 00 00 00 | 01 02 | 01 00")
    fprw = hx(f"{REQ} | 0e 10 | 06 07 02 10 00 15 02 00 00 00 | aa bb | 00 00")
    # RW: old data back, WKC 3 (read 1 + write 2)
    assert c.process(fprw, 0) == hx(f"{REP} | 0e 10 | 06 07 02 10 00 15 02 00 00 00 | 01 02 | 03 00")
    fprd = hx(f"{REQ} | 10 10 | 04 08 02 10 00 00 04 00 00 00 | 00 00 00 00 | 00 00")
    assert c.process(fprd, 0) == hx(f"{REP} | 10 10 | 04 08 02 10 00 00 04 00 00 00 | 11 02 03 00 | 01 00")
    unknown = hx(f"{REQ} | 0e 10 | 04 09 99 99 00 15 02 00 00 00 | 00 00 | 00 00")
    assert c.process(unknown, 0) == hx(f"{REP} | 0e 10 | 04 09 99 99 00 15 02 00 00 00 | 00 00 | 00 00")


def test_aprw_brw_armw_frmw_nop() -> None:
    c = addressed(chain3())
    for i, v in enumerate((0x01, 0x02, 0x04)):
        c.slaves[i].mem[0x1500] = v
    aprw = hx(f"{REQ} | 0d 10 | 03 01 00 00 00 15 01 00 00 00 | 10 | 00 00")
    assert c.process(aprw, 0) == hx(f"{REP} | 0d 10 | 03 01 03 00 00 15 01 00 00 00 | 01 | 03 00")
    assert c.slaves[0].mem[0x1500] == 0x10
    brw = hx(f"{REQ} | 0d 10 | 09 02 00 00 00 15 01 00 00 00 | 20 | 00 00")
    # OR of the old values 0x10 | 0x02 | 0x04 | 0x20 sent; 3 per slave
    assert c.process(brw, 0) == hx(f"{REP} | 0d 10 | 09 02 03 00 00 15 01 00 00 00 | 36 | 09 00")
    assert [s.mem[0x1500] for s in c.slaves] == [0x20, 0x20, 0x20]
    c.slaves[1].mem[0x1500] = 0x55
    armw = hx(f"{REQ} | 0d 10 | 0d 03 ff ff 00 15 01 00 00 00 | 00 | 00 00")
    # position 1 reads 0x55, the others write it on... in wire order: slave 0 wrote 0x00 first
    assert c.process(armw, 0) == hx(f"{REP} | 0d 10 | 0d 03 02 00 00 15 01 00 00 00 | 55 | 03 00")
    assert [s.mem[0x1500] for s in c.slaves] == [0x00, 0x55, 0x55]
    frmw = hx(f"{REQ} | 0d 10 | 0e 04 01 10 00 15 01 00 00 00 | 77 | 00 00")
    assert c.process(frmw, 0) == hx(f"{REP} | 0d 10 | 0e 04 01 10 00 15 01 00 00 00 | 00 | 03 00")
    assert [s.mem[0x1500] for s in c.slaves] == [0x00, 0x00, 0x00]
    nop = hx(f"{REQ} | 0d 10 | 00 05 01 10 00 15 01 00 00 00 | 99 | 07 00")
    assert c.process(nop, 0) == hx(f"{REP} | 0d 10 | 00 05 01 10 00 15 01 00 00 00 | 99 | 07 00")


def test_logical_commands_through_fmmus() -> None:
    c = chain3()
    plan = bring_up(c)
    # image: outputs 3 x u16 at 0..5, inputs 3 x u16 at 6..11
    assert (plan.out_bytes, plan.in_bytes, plan.expected_wkc) == (6, 6, 9)
    lrw = hx(f"{REQ} | 18 10 | 0c 01 00 00 00 00 0c 00 00 00 | 34 12 78 56 bc 9a 00 00 00 00 00 00 | 00 00")
    # inputs of this frame were computed before it: zeros; read 1 + write 2 per slave
    assert c.process(lrw, 1_000_000) == hx(
        f"{REP} | 18 10 | 0c 01 00 00 00 00 0c 00 00 00 | 34 12 78 56 bc 9a 00 00 00 00 00 00 | 09 00"
    )
    # the loopback application returned the outputs into the inputs for the next frame
    assert c.process(lrw, 2_000_000) == hx(
        f"{REP} | 18 10 | 0c 01 00 00 00 00 0c 00 00 00 | 34 12 78 56 bc 9a 34 12 78 56 bc 9a | 09 00"
    )
    lrd = hx(f"{REQ} | 12 10 | 0a 02 06 00 00 00 06 00 00 00 | 00 00 00 00 00 00 | 00 00")
    assert c.process(lrd, 3_000_000) == hx(
        f"{REP} | 12 10 | 0a 02 06 00 00 00 06 00 00 00 | 34 12 78 56 bc 9a | 03 00"
    )
    lwr = hx(f"{REQ} | 10 10 | 0b 03 02 00 00 00 04 00 00 00 | 11 11 22 22 | 00 00")
    # LWR over slaves 1 and 2's outputs: 1 per slave written
    assert c.process(lwr, 4_000_000) == hx(
        f"{REP} | 10 10 | 0b 03 02 00 00 00 04 00 00 00 | 11 11 22 22 | 02 00"
    )
    assert c.slaves[2].od.get_value(0x7000, 1) == 0x2222


def test_several_datagrams_in_one_frame() -> None:
    c = addressed(chain3())
    req = build_master_frame(
        [
            Datagram.physical(Command.BRD, 0, 0x0130, bytes(2), idx=1),
            Datagram.physical(Command.FPRD, 0x1003, 0x0010, bytes(2), idx=1),
            Datagram.physical(Command.BWR, 0, 0x1500, b"\x42", idx=1),
        ]
    )
    reply = c.process(req, 0)
    assert reply is not None and len(reply) == len(req)
    a, b, w = decode_frame(reply).datagrams
    assert (a.data, a.wkc, b.data, b.wkc, w.wkc) == (b"\x01\x00", 3, b"\x03\x10", 1, 3)
    assert [d.more for d in (a, b, w)] == [True, True, False]


# -- AL state machine --


def al(c: EscChain, i: int, value: int) -> tuple[int, int]:
    exchange(c, [Datagram.physical(Command.FPWR, STATION_BASE + i, 0x0120, struct.pack("<H", value))], 0)
    (d,) = exchange(c, [Datagram.physical(Command.FPRD, STATION_BASE + i, 0x0130, bytes(6))], 0)
    status, _, code = struct.unpack("<HHH", d.data)
    return status, code


def test_invalid_transition_sets_error_and_ack_clears_it() -> None:
    c = addressed(chain3())
    assert al(c, 0, AlState.OP) == (AlState.INIT | 0x10, 0x0011)
    assert al(c, 0, AlState.PRE_OP) == (AlState.INIT | 0x10, 0x0011)  # no way up without ack
    assert al(c, 0, AlState.INIT | 0x10) == (AlState.INIT, 0)  # acknowledged
    assert al(c, 0, 0x5) == (AlState.INIT | 0x10, 0x0012)  # unknown state
    assert al(c, 0, 0x5 | 0x10) == (AlState.INIT | 0x10, 0x0012)


def test_preop_needs_mailbox_sms() -> None:
    c = addressed(chain3())
    assert al(c, 0, AlState.PRE_OP) == (AlState.INIT | 0x10, 0x0016)


def test_safeop_refused_with_wrong_sm_lengths() -> None:
    c = chain3()
    bring_up(c)
    assert al(c, 0, AlState.PRE_OP) == (AlState.PRE_OP, 0)
    exchange(c, [Datagram.physical(Command.FPWR, STATION_BASE, 0x0812, struct.pack("<H", 3))], 0)
    assert al(c, 0, AlState.SAFE_OP) == (AlState.PRE_OP | 0x10, 0x001D)
    exchange(c, [Datagram.physical(Command.FPWR, STATION_BASE, 0x0812, struct.pack("<H", 2))], 0)
    exchange(c, [Datagram.physical(Command.FPWR, STATION_BASE, 0x081A, struct.pack("<H", 4))], 0)
    assert al(c, 0, AlState.SAFE_OP | 0x10) == (AlState.PRE_OP | 0x10, 0x001E)
    exchange(c, [Datagram.physical(Command.FPWR, STATION_BASE, 0x081A, struct.pack("<H", 2))], 0)
    assert al(c, 0, AlState.SAFE_OP | 0x10) == (AlState.SAFE_OP, 0)


def test_process_data_watchdog_drops_to_safeop() -> None:
    c = chain3()
    plan = bring_up(c, now_ns=0)
    c.process(plan.lrw(), 1_000_000)
    c.tick(50_000_000)
    assert c.slaves[0].state == AlState.OP
    c.tick(200_000_000)  # > 100 ms without outputs
    assert all(s.state == AlState.SAFE_OP and s.error and s.status_code == 0x001B for s in c.slaves)


def test_watchdog_of_slaves_on_the_copy_plans() -> None:
    """Slaves without an application take the chain's copy plans (no Esc.cycle): the watchdog still holds."""
    c = EscChain.from_maps([io16()] * 3, app=None)
    plan = bring_up(c, now_ns=0)
    for k in range(1, 60):
        reply = c.process(plan.lrw(), k * 1_000_000)
        assert reply is not None
    assert all(s.fast for s in c.slaves)
    assert all(s.state == AlState.OP for s in c.slaves)
    brd = [Datagram.physical(Command.BRD, 0, 0x0130, bytes(2))]
    exchange(c, brd, 150_000_000)  # 91 ms after the last outputs: still within 100 ms
    assert all(s.state == AlState.OP for s in c.slaves)
    exchange(c, brd, 200_000_000)  # > 100 ms without outputs: the next frame finds it
    assert all(s.state == AlState.SAFE_OP and s.error and s.status_code == 0x001B for s in c.slaves)


# -- SII through the EEPROM interface --


def eeprom_read(c: EscChain, i: int, word: int) -> bytes:
    st = STATION_BASE + i
    exchange(c, [Datagram.physical(Command.FPWR, st, 0x0502, struct.pack("<HHH", 0x0100, word, 0))], 0)
    (s,) = exchange(c, [Datagram.physical(Command.FPRD, st, 0x0502, bytes(2))], 0)
    assert struct.unpack("<H", s.data)[0] & 0x8000 == 0  # not busy
    (d,) = exchange(c, [Datagram.physical(Command.FPRD, st, 0x0508, bytes(8))], 0)
    return d.data


def test_sii_identity_and_name_through_eeprom_interface() -> None:
    c = addressed(chain3())
    assert eeprom_read(c, 1, 0x08)[:8] == struct.pack("<II", 0x2, 0x1234)
    assert eeprom_read(c, 1, 0x18)[:8] == struct.pack("<HHHH", 0x1000, 128, 0x1080, 128)
    assert eeprom_read(c, 1, 0x1C)[:2] == b"\x0c\x00"  # CoE and FoE
    assert eeprom_read(c, 1, 0x14)[:8] == struct.pack("<HHHH", 0x1000, 512, 0x1200, 512)  # bootstrap mailbox
    image = c.slaves[1].sii
    assert image.name == "io16"
    assert [s.type for s in image.sms] == [1, 2, 3, 4]
    assert SiiImage(bytes(image.data)).name == "io16"  # a raw image loads too


def test_sii_of_the_maxon_map() -> None:
    sii = build_sii(load_drive_map(MAXON))
    assert (sii.vendor_id, sii.product_code, sii.name) == (0xFB, 0x63500000, "maxon_epos4_50_5")
    assert [(s.type, s.length) for s in sii.sms][2:] == [(3, 23), (4, 25)]


# -- CoE over the mailbox --


def mbx_exchange(c: EscChain, i: int, coe: bytes, counter: int) -> bytes:
    st = STATION_BASE + i
    buf = struct.pack("<HHBB", len(coe), 0, 0, 0x03 | counter << 4) + coe
    (w,) = exchange(c, [Datagram.physical(Command.FPWR, st, 0x1000, buf.ljust(128, b"\0"))], 0)
    assert w.wkc == 1
    (s,) = exchange(c, [Datagram.physical(Command.FPRD, st, 0x080D, bytes(1))], 0)
    assert s.data[0] & 0x08
    (r,) = exchange(c, [Datagram.physical(Command.FPRD, st, 0x1080, bytes(128))], 0)
    assert r.wkc == 1
    length = struct.unpack_from("<H", r.data)[0]
    return r.data[6 : 6 + length]


def preop(c: EscChain) -> EscChain:
    bring_up(c)
    for i in range(len(c)):
        al(c, i, AlState.PRE_OP)
    return c


def test_sdo_expedited_upload_download_and_abort() -> None:
    c = preop(chain3())
    up = mbx_exchange(c, 0, hx("00 20 40 18 10 01 00 00 00 00"), 1)
    assert up == hx("00 30 43 18 10 01 02 00 00 00")  # vendor id 0x00000002, 4 bytes expedited
    down = mbx_exchange(c, 0, hx("00 20 2b 00 70 01 cd ab 00 00"), 2)
    assert down == hx("00 30 60 00 70 01 00 00 00 00")
    assert c.slaves[0].od.get_value(0x7000, 1) == 0xABCD
    missing = mbx_exchange(c, 0, hx("00 20 40 00 20 00 00 00 00 00"), 3)
    assert missing == hx("00 20 80 00 20 00 00 00 02 06")  # abort 0x06020000 as SDO request
    ro = mbx_exchange(c, 0, hx("00 20 23 18 10 01 00 00 00 00"), 4)
    assert ro == hx("00 20 80 18 10 01 02 00 01 06")  # 0x06010002 read only


def test_repeated_mailbox_write_is_not_applied_twice() -> None:
    c = preop(chain3())
    od = c.slaves[0].od
    od.set_value(0x7000, 1, 0)
    mbx_exchange(c, 0, hx("00 20 2b 00 70 01 05 00 00 00"), 5)
    od.set_value(0x7000, 1, 0)
    # the same frame again (a resend, same counter): not executed, no new answer
    coe = hx("00 20 2b 00 70 01 05 00 00 00")
    buf = struct.pack("<HHBB", len(coe), 0, 0, 0x03 | 5 << 4) + coe
    exchange(c, [Datagram.physical(Command.FPWR, STATION_BASE, 0x1000, buf.ljust(128, b"\0"))], 0)
    assert od.get_value(0x7000, 1) == 0
    assert c.slaves[0].mailbox.duplicates == 1


def test_lost_mailbox_answer_is_repeated_on_request() -> None:
    c = preop(chain3())
    first = mbx_exchange(c, 0, hx("00 20 40 18 10 02 00 00 00 00"), 1)
    (s,) = exchange(c, [Datagram.physical(Command.FPRD, STATION_BASE, 0x080D, bytes(2))], 0)
    assert s.data[0] & 0x08 == 0  # read: empty
    (r,) = exchange(c, [Datagram.physical(Command.FPRD, STATION_BASE, 0x1080, bytes(128))], 0)
    assert r.wkc == 0  # empty mailbox: read denied
    toggled = bytes([s.data[0], s.data[1] ^ 0x02])
    exchange(c, [Datagram.physical(Command.FPWR, STATION_BASE, 0x080D, toggled)], 0)
    (ack,) = exchange(c, [Datagram.physical(Command.FPRD, STATION_BASE, 0x080F, bytes(1))], 0)
    assert ack.data[0] & 0x02 == toggled[1] & 0x02
    (again,) = exchange(c, [Datagram.physical(Command.FPRD, STATION_BASE, 0x1080, bytes(128))], 0)
    assert again.wkc == 1 and again.data[6:16] == first


def test_segmented_upload_of_a_long_string() -> None:
    drive = drive_map_from_text(IO16.replace("name: io16", "name: " + "x" * 200))
    c = preop(EscChain.from_maps([drive], app=None))
    init = mbx_exchange(c, 0, hx("00 20 40 08 10 00 00 00 00 00"), 1)
    assert init[2] == 0x41 and struct.unpack_from("<I", init, 6)[0] == 200
    data = bytearray(init[10:])
    toggle = 0
    for counter in range(2, 8):
        seg = mbx_exchange(c, 0, bytes([0x00, 0x20, 0x60 | toggle, 0, 0, 0, 0, 0, 0, 0]), counter)
        assert seg[2] & 0x10 == toggle
        data += seg[3:]
        toggle ^= 0x10
        if seg[2] & 0x01:
            break
    assert bytes(data[:200]) == b"x" * 200


def test_mapping_change_changes_process_data() -> None:
    od = ObjectDictionary.from_drive_map(load_drive_map(MAXON))
    pre = CommState.PRE_OPERATIONAL
    od.write(0x1C13, 0, b"\x00", state=pre)
    with pytest.raises(SdoAbortError) as exc:
        od.write(0x1A03, 1, bytes(4), state=pre)
    assert exc.value.code == 0x06010003  # sub 0 must be 0 first
    od.write(0x1A03, 0, b"\x00", state=pre)
    od.write(0x1A03, 0, b"\x02", state=pre)
    od.write(0x1C13, 0, b"\x01", state=pre)
    assert [c.index for c in od.assigned_pdos(0x1C13)[0].channels] == [0x6041, 0x6064]
    with pytest.raises(SdoAbortError) as exc:
        od.write(0x1A03, 0, b"\x00", state=CommState.SAFE_OPERATIONAL)
    assert exc.value.code == 0x08000022
    with pytest.raises(SdoAbortError) as exc:
        od.write(0x1A03, 1, struct.pack("<I", 0x12340020), state=pre)
    assert exc.value.code == 0x06010003


# -- fault hooks --


def test_fault_hooks() -> None:
    c = chain3()
    plan = bring_up(c)
    c.drop_frames(1)
    assert c.process(plan.lrw(), 1) is None
    c.corrupt_wkc(-2, 1)
    assert decode_frame(c.process(plan.lrw(), 2) or b"").datagrams[0].wkc == plan.expected_wkc - 2
    assert decode_frame(c.process(plan.lrw(), 3) or b"").datagrams[0].wkc == plan.expected_wkc
    c.delay_frames(0.01)
    c.process(plan.lrw(), 4)
    assert c.take_delay() == 0.01 and c.take_delay() == 0.0
    c.power_cycle(1)
    assert c.slaves[1].state == AlState.INIT and c.slaves[1].station_address == 0
    assert decode_frame(c.process(plan.lrw(), 5) or b"").datagrams[0].wkc == plan.expected_wkc - 3
    c.refuse_state(0, AlState.OP, 0x001D)
    assert al(c, 0, AlState.SAFE_OP) == (AlState.SAFE_OP, 0)
    assert al(c, 0, AlState.OP) == (AlState.SAFE_OP | 0x10, 0x001D)
    c.abort_sdo(2, 0x1018, 1, 0x08000020)
    with pytest.raises(SdoAbortError):
        c.slaves[2].od.read(0x1018, 1)
    c.clear_faults()
    assert c.slaves[2].od.read(0x1018, 1) == struct.pack("<I", 2)
