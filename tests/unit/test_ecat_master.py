"""One EtherCAT adapter (fieldbus.backends.ecat_master): pysoem's errors are mapped in one place only.

The mapping is checked against pysoem's own exception classes (raised by a
stand-in call: a mock for this one function; the transfers themselves run over
veth against the emulator in tests/integration/test_sdo_cli.py, test_scan.py and
test_pysoem_emulator.py). The structural test reads the package with ast: any
module but the adapter that catches a pysoem error or makes SOEM's register,
config_init or mailbox-receive calls is a second mapping.
"""

from __future__ import annotations

import ast
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

pysoem = pytest.importorskip("pysoem", reason="the EtherCAT adapter needs pysoem (fieldbus[ethercat])")

from fieldbus.backends import ecat_master  # noqa: E402
from fieldbus.errors import BusTimeoutError, FieldbusError, SdoAbortError  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
ADAPTER = ROOT / "fieldbus" / "backends" / "ecat_master.py"
# pysoem's API implemented on the in-process chain: it raises pysoem's errors and defines its register calls
# for the adapter to map, it maps nothing itself
TRANSPORT = ROOT / "fieldbus" / "backends" / "ecat_inprocess.py"
PYSOEM_ERRORS = {"SdoError", "Emergency", "WkcError", "MailboxError", "PacketError"}
SOEM_CALLS = {"_fprd", "_fpwr", "config_init", "mbx_receive"}


def pysoem_error_uses(source: str) -> list[str]:
    """``line: what`` for each pysoem error named and each SOEM register/bring-up call made in ``source``."""
    out = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Attribute) and node.attr in PYSOEM_ERRORS:
            out.append(f"{node.lineno}: pysoem.{node.attr}")
        elif (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Attribute)
            and node.func.attr in SOEM_CALLS
        ):
            out.append(f"{node.lineno}: .{node.func.attr}()")
    return out


def test_only_the_adapter_maps_pysoem_errors_or_calls_soem_registers() -> None:
    found = {
        str(p.relative_to(ROOT)): uses
        for p in (ROOT / "fieldbus").rglob("*.py")
        if p not in (ADAPTER, TRANSPORT) and (uses := pysoem_error_uses(p.read_text()))
    }
    assert found == {}
    assert pysoem_error_uses(ADAPTER.read_text())  # the checker sees the adapter's own mapping


def test_the_checker_sees_a_copied_mapping() -> None:
    copy = "try:\n    s.sdo_read(1, 0)\nexcept pysoem.SdoError as e:\n    pass\nraw = s._fprd(0x130, 2)\n"
    assert sorted(pysoem_error_uses(copy)) == ["3: pysoem.SdoError", "5: ._fprd()"]


def raising(*errors: BaseException, result: Any = b"\x01") -> Callable[[], Any]:
    """A call that raises ``errors`` one per call, then returns ``result``."""
    left = list(errors)

    def call() -> Any:
        if left:
            raise left.pop(0)
        return result

    return call


def test_an_abort_is_an_sdo_abort_error_at_once() -> None:
    call = raising(pysoem.SdoError(1, 0x6060, 0, 0x06090011, "no sub-index"))
    with pytest.raises(SdoAbortError) as err:
        ecat_master.sdo(call, index=0x6060, sub_index=0, slave="slave 1 (drive)", what="read", tries=3)
    assert (err.value.code, err.value.index, err.value.sub_index) == (0x06090011, 0x6060, 0)
    assert str(err.value).startswith("slave 1 (drive): SDO abort 0x06090011")


def test_no_answer_is_tried_again_then_a_timeout_naming_the_object() -> None:
    assert ecat_master.sdo(raising(pysoem.WkcError()), index=1, sub_index=0, slave="a", what="read", tries=2)
    call = raising(pysoem.WkcError(), pysoem.MailboxError(1, 5, "mailbox"), pysoem.PacketError(1, 3))
    with pytest.raises(BusTimeoutError) as err:
        ecat_master.sdo(
            call, index=0x1018, sub_index=4, slave="a", who="bus 'x' slave a", what="read", tries=3
        )
    assert str(err.value).startswith("bus 'x' slave a: no answer to SDO read 0x1018:04 after 3 tries")


def test_an_emergency_instead_of_the_answer_is_handed_over_and_the_transfer_tried_again() -> None:
    seen: list[tuple[int, int]] = []
    call = raising(pysoem.Emergency(1, 0x2310, 0x03, 0, 0, 0), result=b"\x07")
    got = ecat_master.sdo(
        call,
        index=0x6061,
        sub_index=0,
        slave="a",
        what="read",
        tries=2,
        on_emergency=lambda c, r: seen.append((c, r)),
    )
    assert got == b"\x07" and seen == [(0x2310, 0x03)]
    with pytest.raises(BusTimeoutError, match="emergency 0x2310"):
        ecat_master.sdo(
            raising(pysoem.Emergency(1, 0x2310, 3, 0, 0, 0)), index=1, sub_index=0, slave="a", what="write"
        )


def test_a_card_that_cannot_be_opened_names_it_and_the_capability() -> None:
    with pytest.raises(FieldbusError) as err:
        ecat_master.open_card(pysoem.Master(), "no-such-card0", where="bus 'b': ")
    assert str(err.value).startswith("bus 'b': cannot open interface 'no-such-card0'")
    assert "CAP_NET_RAW" in str(err.value)


class _Object:
    def __init__(self, index: int, entries: list[str] | Exception) -> None:
        self.index = index
        self._entries = entries

    @property
    def entries(self) -> list[str]:
        if isinstance(self._entries, Exception):
            raise self._entries
        return self._entries


class _Slave:
    """pysoem's slave as SDO Information sees it: ``od`` (entries read when reached), ``mbx_receive``."""

    def __init__(self, objects: list[_Object], queued: int) -> None:
        self.od = objects
        self.queued = queued  # SDO Information errors SOEM keeps queued
        self.receives = 0

    def mbx_receive(self) -> int:
        self.receives += 1
        if self.queued:
            self.queued -= 1
            raise Exception("queued SDO Information error")  # what pysoem raises for one
        return 0


def test_sdo_information_failing_on_an_entry_is_a_fieldbus_error_and_the_queue_is_emptied() -> None:
    slave = _Slave(
        [_Object(0x1000, []), _Object(0x6000, pysoem.SdoInfoError("no entry 0x6000:01"))], queued=3
    )
    seen = []
    with pytest.raises(FieldbusError, match=r"SDO Information: no entry 0x6000:01"):
        for obj, entries in ecat_master.object_dictionary(slave):
            seen.append((obj.index, entries))
    assert seen == [(0x1000, [])]  # what came before the failure was handed over
    assert (slave.queued, slave.receives) == (0, 4)  # three queued errors popped, then an empty receive


def test_sdo_information_of_chosen_objects_only() -> None:
    slave = _Slave([_Object(0x1000, ["a"]), _Object(0x6000, Exception("not read"))], queued=0)
    assert [(o.index, e) for o, e in ecat_master.object_dictionary(slave, {0x1000})] == [(0x1000, ["a"])]
    assert slave.receives == 1


class _Scanning:
    """A master whose first ``config_init`` calls find nobody (SOEM returns -1 when its broadcast is lost)."""

    def __init__(self, empty_scans: int) -> None:
        self.empty_scans = empty_scans
        self.scans = 0
        self.slaves: list[str] = []

    def config_init(self) -> int:
        self.scans += 1
        self.slaves = [] if self.scans <= self.empty_scans else ["a", "b"]
        return -1 if self.scans <= self.empty_scans else 2


@pytest.mark.parametrize("empty_scans", [0, 1, ecat_master.SCAN_TRIES - 1])
def test_a_scan_that_finds_nobody_is_made_again(empty_scans: int) -> None:
    master = _Scanning(empty_scans)
    assert ecat_master.find_slaves(master) == ["a", "b"]
    assert master.scans == empty_scans + 1


def test_a_segment_is_empty_after_every_scan_found_nobody() -> None:
    master = _Scanning(empty_scans=99)
    assert ecat_master.find_slaves(master) == []
    assert master.scans == ecat_master.SCAN_TRIES


def test_with_a_wait_the_scan_goes_on_until_a_restarting_device_answers() -> None:
    """After a firmware update a device may restart: the rescan keeps looking for ``wait_s`` (virtual
    time here: each scan is SOEM's 20 ms wait)."""
    master = _Scanning(empty_scans=ecat_master.SCAN_TRIES + 30)
    assert ecat_master.find_slaves(master, wait_s=5.0, clock=lambda: master.scans * 0.02) == ["a", "b"]
    assert master.scans == ecat_master.SCAN_TRIES + 31


def test_with_a_wait_an_empty_segment_is_empty_once_the_wait_has_passed() -> None:
    master = _Scanning(empty_scans=10_000)
    assert ecat_master.find_slaves(master, wait_s=1.0, clock=lambda: master.scans * 0.02) == []
    assert master.scans == 50  # 1 s of 20 ms scans: more than SCAN_TRIES, not for ever
