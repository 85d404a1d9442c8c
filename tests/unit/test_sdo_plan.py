"""SDO plans, step by step, against the CoE (ETG.1000.6) and CiA 301 order."""

from __future__ import annotations

from pathlib import Path

import pytest

from fieldbus.core.pdo import drive_map_from_text, load_drive_map
from fieldbus.core.sdo import StepKind, abort_name, canopen_plan, coe_plan
from fieldbus.errors import FieldbusError, SdoAbortError

TWO_PDO = """
vendor_id: 1
product_id: 2
sdo:
  - {index: 0x6060, sub_index: 0, type: int8, value: 8}
rpdo:
  - index: 0x1600
    channels:
      - {index: 0x6040, sub_index: 0, type: uint16}
      - {index: 0x6060, sub_index: 0, type: int8}
      - {index: 0, sub_index: 0, type: bit8}
  - index: 0x1601
    channels:
      - {index: 0x607a, sub_index: 0, type: int32}
tpdo:
  - index: 0x1a00
    channels:
      - {index: 0x6041, sub_index: 0, type: uint16}
      - {index: 0x6064, sub_index: 0, type: int32}
"""


def steps(plan):  # type: ignore[no-untyped-def]
    return [
        (s.kind, s.index, s.sub_index, s.data.hex(), None if s.readback is None else s.readback.hex())
        for s in plan.steps
    ]


W, V = StepKind.WRITE, StepKind.VERIFY


def test_coe_plan_order() -> None:
    plan = coe_plan(drive_map_from_text(TWO_PDO))
    assert plan.bus == "coe"
    assert steps(plan) == [
        (W, 0x1C12, 0, "00", None),  # SM2 assignment cleared first
        (W, 0x1C13, 0, "00", None),
        (W, 0x1600, 0, "00", None),  # mapping count 0, entries, count
        (W, 0x1600, 1, "10004060", "10004060"),
        (W, 0x1600, 2, "08006060", "08006060"),
        (W, 0x1600, 3, "08000000", "08000000"),  # gap: index 0, 8 bits
        (W, 0x1600, 0, "03", "03"),
        (W, 0x1601, 0, "00", None),
        (W, 0x1601, 1, "20007a60", "20007a60"),
        (W, 0x1601, 0, "01", "01"),
        (W, 0x1A00, 0, "00", None),
        (W, 0x1A00, 1, "10004160", "10004160"),
        (W, 0x1A00, 2, "20006460", "20006460"),
        (W, 0x1A00, 0, "02", "02"),
        (W, 0x1C12, 1, "0016", "0016"),  # assignment entries (u16), then count
        (W, 0x1C12, 2, "0116", "0116"),
        (W, 0x1C12, 0, "02", "02"),
        (W, 0x1C13, 1, "001a", "001a"),
        (W, 0x1C13, 0, "01", "01"),
        (W, 0x6060, 0, "08", "08"),  # the map's own start-up SDOs last
    ]
    assert len(plan.checks) == 15 and all(s.readback == s.data for s in plan.checks)


def test_coe_fixed_pdo_is_verified_not_written() -> None:
    text = TWO_PDO.replace("  - index: 0x1601\n", "  - index: 0x1601\n    fixed: true\n")
    plan = coe_plan(drive_map_from_text(text))
    fixed = [s for s in plan.steps if s.index == 0x1601]
    assert [(s.kind, s.sub_index, s.readback.hex() if s.readback else None) for s in fixed] == [
        (V, 1, "20007a60"),
        (V, 0, "01"),
    ]
    assert 0x1601 in [
        int.from_bytes(s.data, "little") for s in plan.steps if s.index == 0x1C12 and s.sub_index
    ]


def test_coe_plan_without_coe() -> None:
    text = TWO_PDO.replace(
        "sdo:\n  - {index: 0x6060, sub_index: 0, type: int8, value: 8}\n", "ethercat: {coe: false}\n"
    )
    assert coe_plan(drive_map_from_text(text)).steps == ()
    with pytest.raises(FieldbusError, match="need CoE"):
        coe_plan(drive_map_from_text(TWO_PDO + "ethercat: {coe: false}\n"))


CAN = """
vendor_id: 1
product_id: 2
canopen:
  heartbeat_ms: 50
  pdo:
    - {index: 0x1a00, transmission_type: 1, inhibit_time: 10, event_timer: 0}
rpdo:
  - index: 0x1601
    channels:
      - {index: 0x6040, sub_index: 0, type: uint16}
      - {index: 0x607a, sub_index: 0, type: int32}
tpdo:
  - index: 0x1a00
    channels:
      - {index: 0x6041, sub_index: 0, type: uint16}
"""


def test_canopen_plan_follows_cia301_sequence() -> None:
    plan = canopen_plan(drive_map_from_text(CAN), node_id=5)
    assert steps(plan) == [
        # unused RPDO1,3,4 and TPDO2,3,4 disabled (bit 31 set on the default COB-ID)
        (W, 0x1400, 1, (0x80000205).to_bytes(4, "little").hex(), (0x80000205).to_bytes(4, "little").hex()),
        (W, 0x1402, 1, (0x80000405).to_bytes(4, "little").hex(), (0x80000405).to_bytes(4, "little").hex()),
        (W, 0x1403, 1, (0x80000505).to_bytes(4, "little").hex(), (0x80000505).to_bytes(4, "little").hex()),
        (W, 0x1801, 1, (0x80000285).to_bytes(4, "little").hex(), (0x80000285).to_bytes(4, "little").hex()),
        (W, 0x1802, 1, (0x80000385).to_bytes(4, "little").hex(), (0x80000385).to_bytes(4, "little").hex()),
        (W, 0x1803, 1, (0x80000485).to_bytes(4, "little").hex(), (0x80000485).to_bytes(4, "little").hex()),
        # RPDO2: COB-ID invalid, transmission type, count 0, entries, count, COB-ID valid
        (W, 0x1401, 1, "05030080", None),
        (W, 0x1401, 2, "01", "01"),
        (W, 0x1601, 0, "00", None),
        (W, 0x1601, 1, "10004060", "10004060"),
        (W, 0x1601, 2, "20007a60", "20007a60"),
        (W, 0x1601, 0, "02", "02"),
        (W, 0x1401, 1, "05030000", "05030000"),
        # TPDO1 with inhibit time and event timer
        (W, 0x1800, 1, "85010080", None),
        (W, 0x1800, 2, "01", "01"),
        (W, 0x1800, 3, "0a00", "0a00"),
        (W, 0x1800, 5, "0000", "0000"),
        (W, 0x1A00, 0, "00", None),
        (W, 0x1A00, 1, "10004160", "10004160"),
        (W, 0x1A00, 0, "01", "01"),
        (W, 0x1800, 1, "85010000", "85010000"),
        (W, 0x1017, 0, "3200", "3200"),  # heartbeat producer 50 ms
    ]


def test_canopen_plan_needs_section_and_valid_node() -> None:
    with pytest.raises(FieldbusError, match="no 'canopen' section"):
        canopen_plan(drive_map_from_text(TWO_PDO), 1)
    with pytest.raises(FieldbusError, match="node id 0"):
        canopen_plan(drive_map_from_text(CAN), 0)


def test_pdo_beyond_4_needs_explicit_cob_id() -> None:
    text = CAN.replace("  - index: 0x1601\n", "  - index: 0x1604\n")
    with pytest.raises(FieldbusError, match="RPDO5: only PDO 1-4 have a default COB-ID"):
        drive_map_from_text(text)


def test_interop_epos4_plan_sizes(interop_dir: Path) -> None:
    plan = coe_plan(load_drive_map(interop_dir / "maxon_epos4_50_5.yaml"))
    assert len(plan.steps) == 2 + (1 + 8 + 1) + (1 + 9 + 1) + 4 + 2


def test_abort_error_names_code() -> None:
    e = SdoAbortError(0x06020000, index=0x6060, sub_index=0, slave="hip")
    assert e.name == "Object does not exist in the object dictionary" == abort_name(0x06020000)
    assert str(e) == "hip: SDO abort 0x06020000 'Object does not exist in the object dictionary' on 0x6060:00"
    assert abort_name(0x12345678) == "unknown abort code"


def test_a_transfer_without_answer_is_tried_again_at_the_next_step() -> None:
    """Recovery runs a plan one SDO per cycle with a short timeout: a lost answer costs a cycle, not the plan."""
    from fieldbus.backends.sdo_exec import plan_transfers
    from fieldbus.errors import BusTimeoutError

    plan = coe_plan(drive_map_from_text(TWO_PDO, "two.yaml"))
    od: dict[tuple[int, int], bytes] = {}
    silent = {(0x1600, 2): 1, (0x6060, 0): 2}  # these stay unanswered this many times

    def write(index: int, sub: int, data: bytes) -> None:
        if silent.get((index, sub), 0):
            silent[(index, sub)] -= 1
            raise BusTimeoutError(f"no answer to 0x{index:04X}:{sub:02X}")
        od[(index, sub)] = data

    def read(index: int, sub: int, size: int) -> bytes:
        return od.get((index, sub), bytes(size))

    gen = plan_transfers(plan, write, read, slave="j0", tries=3)
    yields = 0
    with pytest.raises(StopIteration) as done:
        while True:
            next(gen)
            yields += 1
    writes = [s for s in plan.steps if s.kind is StepKind.WRITE]
    assert done.value.value == len(writes) + len(plan.checks)
    assert yields == len(writes) + len(plan.checks) + 3  # one more step per lost answer
    silent[(0x6060, 0)] = 3  # more than the tries: the plan fails with the object named
    with pytest.raises(BusTimeoutError, match="0x6060:00"):
        for _ in plan_transfers(plan, write, read, slave="j0", tries=3):
            pass
