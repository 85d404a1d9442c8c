"""Errors by name: the CiA 402 drive codes, and a drive's 0x1003 history read through the cycle.

On the CANopen emulator over python-can's virtual bus: the node records each
EMCY it sends in its pre-defined error field 0x1003 (newest at sub 1), and
``fieldbus.diagnosis.ErrorHistory`` reads it back through
``Operational.submit_sdo_read`` while the cycle runs. The names come from our
own table (fieldbus.core.emcy); the codes travel through our emulator and our
backend, so this test can only use our own code on both sides.
"""

from __future__ import annotations

import itertools
import json
import time
from pathlib import Path

import pytest

import fieldbus
from fieldbus.core.emcy import emcy_name
from fieldbus.diagnosis import ErrorHistory

DEMO_MAP = Path(fieldbus.__file__).resolve().parent / "data" / "demo_joint.yaml"
_channels = itertools.count()


@pytest.mark.parametrize(
    ("code", "name"),
    [
        (0x2310, "continuous over-current"),
        (0x3210, "DC link over-voltage"),
        (0x4210, "excess temperature device"),
        (0x5441, "contact 1 (manufacturer specific)"),
        (0x7121, "motor blocked"),
        (0x7305, "incremental sensor 1 fault"),
        (0x8611, "following error"),
        (0x8612, "reference limit"),
        (0x8311, "excess torque"),
        (0x2350, "load level fault (I2t, thermal state)"),
        (0xFF42, "device specific (0xFF42)"),  # the manufacturer's: left as a number
    ],
)
def test_cia402_drive_codes_by_name(code: int, name: str) -> None:
    assert emcy_name(code) == name


def test_error_history_over_canopen_names_the_emergencies_newest_first(tmp_path: Path) -> None:
    can = pytest.importorskip("can")
    from sim_slaves.canopen import CanopenSimulator

    channel = f"fb-history-{next(_channels)}-{time.monotonic_ns()}"
    net_file = tmp_path / "net.yaml"
    net_file.write_text(
        "cycle_time_us: 5000\nreceive_timeout_us: 50000\nbuses:\n"
        f"  - {{name: bus, type: canopen, interface: {channel}, can_interface: virtual,\n"
        f"     slaves: [{{name: j, map: {json.dumps(str(DEMO_MAP))}, node_id: 4}}]}}\n"
    )
    drive = fieldbus.load_drive_map(DEMO_MAP)
    with (
        can.Bus(interface="virtual", channel=channel) as bus,
        CanopenSimulator(bus, [(drive, 4)], dt_s=0.005) as sim,
        fieldbus.open_network(net_file) as net,
    ):
        op = net.bring_up()
        empty = ErrorHistory(op, "bus", "j")
        got = None
        for _ in range(500):
            op.exchange()
            got = empty.poll()
            if got is not None:
                break
        assert got == []
        sim.send_emergency(4, 0x2310, data=b"\x34\x12")
        sim.send_emergency(4, 0x8611)
        history = ErrorHistory(op, "bus", "j")
        entries = None
        for _ in range(500):
            op.exchange()
            entries = history.poll()
            if entries is not None:
                break
        assert entries is not None
        assert [(e.code, e.name, e.info) for e in entries] == [
            (0x8611, "following error", 0),
            (0x2310, "continuous over-current", 0x1234),
        ]
        assert str(entries[1]) == "0x2310 continuous over-current (info 0x1234)"
    assert not sim.errors
