"""A bus fault keeps its structure: every miss has a :class:`fieldbus.BusFault` of its kind in
``BusStatus.fault`` (this cycle) and ``last_fault`` (kept), beside the text in ``BusStatus.error``.

EtherCAT kinds on the sim backend (real frames against the emulated ESC chain, its fault hooks
losing a frame or falsifying a working counter; a virtual clock, so a busy machine makes no miss);
a raised send or receive is a backend method replaced for one call (a mock for one function).
Bus-off: the raw-CAN backend on python-can's virtual bus, the MIT motor emulators on the same
channel and an injected error frame of class CAN_ERR_BUSOFF.
"""

from __future__ import annotations

import itertools
import json
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

import fieldbus
from fieldbus import BusFault, FaultKind
from fieldbus.commands.demo import DEMO_MAP
from fieldbus.core.safety import Verdict
from fieldbus.platform.clock import VirtualClock

_channels = itertools.count()


@pytest.fixture
def arm(tmp_path: Path) -> Iterator[tuple[fieldbus.Network, fieldbus.Operational]]:
    f = tmp_path / "net.yaml"
    m = json.dumps(str(DEMO_MAP))
    f.write_text(
        "cycle_time_us: 1000\nreceive_timeout_us: 5000\nsafe_stop_after: 5\nbuses:\n"
        f"  - {{name: arm, type: ethercat, interface: sim0, slaves: [{{name: 'j{{i}}', map: {m}, count: 2}}]}}\n"
    )
    net = fieldbus.open_network(f, backend="sim", clock=VirtualClock())
    try:
        op = net.bring_up()
        for _ in range(3):
            assert op.exchange().fresh
        assert op.result.bus("arm").fault is None and op.result.bus("arm").last_fault is None
        yield net, op
    finally:
        net.close()


def _chain(net: fieldbus.Network) -> Any:
    return net.backend("arm").chain  # type: ignore[attr-defined]  # the emulator's fault hooks


def test_a_lost_frame_is_a_timeout_fault(arm: Any) -> None:
    net, op = arm
    _chain(net).drop_frames(2, process_data=True)
    st = op.exchange().bus("arm")
    assert st.verdict is Verdict.TIMEOUT and st.error is None  # the text field is unchanged: no error
    assert st.fault == BusFault(
        "arm", FaultKind.TIMEOUT, st.expected_wkc, None, "no reply within the receive timeout"
    )
    first = st.fault
    st = op.exchange().bus("arm")
    assert st.fault is first  # the same fault again: not made anew each cycle of an outage
    st = op.exchange().bus("arm")
    assert st.verdict is Verdict.OK and st.fault is None and st.last_fault is first


def test_a_short_working_counter_is_a_wkc_mismatch_with_both_counts(arm: Any) -> None:
    net, op = arm
    _chain(net).corrupt_wkc(-1, 1)
    st = op.exchange().bus("arm")
    assert st.verdict is Verdict.SHORT and st.error is None
    assert st.fault is not None and st.fault.kind is FaultKind.WKC_MISMATCH
    assert (st.fault.expected, st.fault.received) == (st.expected_wkc, st.expected_wkc - 1)
    assert st.fault.text == f"working counter {st.expected_wkc - 1}, expected {st.expected_wkc}"
    assert st.fault.exception is None


@pytest.mark.parametrize("verb", ["send", "receive"])
def test_a_raising_backend_is_a_send_or_receive_error_with_its_type(
    arm: Any, verb: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    net, op = arm
    b = net.backend("arm")

    def boom(*_: object) -> None:
        raise ConnectionResetError(f"{verb} went down")

    monkeypatch.setattr(b, verb, boom)
    st = op.exchange().bus("arm")
    monkeypatch.undo()
    assert st.verdict is Verdict.ERROR and st.error == f"ConnectionResetError: {verb} went down"
    kind = FaultKind.SEND_ERROR if verb == "send" else FaultKind.RECEIVE_ERROR
    assert st.fault == BusFault("arm", kind, st.expected_wkc, None, st.error, "ConnectionResetError")
    assert st.last_fault is st.fault and st.safe_stop  # an error latches at once (S1, S4)
    for _ in range(3):  # the emulator still has the frame the failed receive left behind: drain it
        st = op.exchange().bus("arm")
    assert st.verdict is Verdict.OK and st.fault is None and st.last_fault is not None
    assert st.last_fault.kind is kind


def test_a_fault_is_frozen(arm: Any) -> None:
    net, op = arm
    _chain(net).drop_frames(1, process_data=True)
    fault = op.exchange().bus("arm").fault
    assert fault is not None
    with pytest.raises(AttributeError):
        fault.kind = FaultKind.BUS_OFF  # type: ignore[misc]


def test_a_reported_bus_off_is_a_bus_off_fault(tmp_path: Path) -> None:
    can = pytest.importorskip("can")
    from sim_slaves.mit_motor import MitMotorSimulator

    channel = f"fb-busfault-{next(_channels)}-{time.monotonic_ns()}"
    mit = Path(fieldbus.PDO_MAPS) / "cubemars_ak80_9_mit.yaml"
    f = tmp_path / "can.yaml"
    f.write_text(
        "cycle_time_us: 5000\nreceive_timeout_us: 20000\nsafe_stop_after: 10\nbuses:\n"
        f"  - {{name: bus, type: rawcan, interface: {channel}, can_interface: virtual,\n"
        f"     slaves: [{{name: 'n{{i}}', map: {json.dumps(str(mit))}, node_id: 1, count: 2}}]}}\n"
    )
    drive = fieldbus.load_drive_map(mit)
    with (
        can.Bus(interface="virtual", channel=channel) as bus,
        MitMotorSimulator(bus, [(drive, n) for n in (1, 2)], dt_s=0.005),
        can.Bus(interface="virtual", channel=channel) as injector,
        fieldbus.open_network(f) as net,
    ):
        op = net.bring_up()
        for _ in range(3):
            assert op.exchange().fresh
        injector.send(
            can.Message(arbitration_id=0x040, is_error_frame=True, is_extended_id=False, data=bytes(8))
        )
        st = op.exchange().buses[0]
        assert st.verdict is Verdict.ERROR and st.error is not None and "bus-off" in st.error
        assert st.fault is not None and st.fault.kind is FaultKind.BUS_OFF
        assert (st.fault.bus, st.fault.expected, st.fault.text) == ("bus", 2, st.error)
        assert st.fault.exception is None  # reported by the controller: nothing raised


def test_a_bus_fault_reads_as_one_line_naming_bus_kind_and_counts() -> None:
    """Recordings and /diagnostics show a fault by its str(): the bus, the kind, expected and received."""
    from fieldbus import BusFault, FaultKind

    lost = BusFault("arm", FaultKind.TIMEOUT, 6)
    short = BusFault("arm", FaultKind.WKC_MISMATCH, 6, 4, "working counter 4, expected 6")
    assert str(lost) == "arm: timeout (expected 6, received nothing)"
    assert str(short) == "arm: wkc_mismatch (expected 6, received 4): working counter 4, expected 6"
