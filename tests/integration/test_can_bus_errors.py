"""A failing CAN driver: send/receive raise BusIoError (counted), stop() and close() never raise (issue 23,
defect 4).

The driver is python-can's virtual bus behind a thin python-can bus whose
``send`` raises ``CanOperationError("Transmit buffer full")`` - what socketcan
raises when no node acknowledges (an unplugged cable) - or whose receive fails,
on demand. The nodes are the emulators on the same virtual channel.
"""

from __future__ import annotations

import itertools
import json
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

can = pytest.importorskip("can")

from fieldbus import PDO_MAPS  # noqa: E402
from fieldbus.backends import backend_class  # noqa: E402
from fieldbus.commands.demo import DEMO_MAP  # noqa: E402
from fieldbus.core.network import load_network  # noqa: E402
from fieldbus.core.pdo import load_drive_map  # noqa: E402
from fieldbus.errors import BusIoError  # noqa: E402
from fieldbus.network import Operational, open_network  # noqa: E402
from sim_slaves.canopen import CanopenSimulator  # noqa: E402
from sim_slaves.mit_motor import MitMotorSimulator  # noqa: E402

pytestmark = pytest.mark.timeout(120)
MIT_MAP = Path(PDO_MAPS) / "cubemars_ak80_9_mit.yaml"
_channels = itertools.count()


class FailingBus(can.BusABC):
    """A virtual bus whose send or receive fails like socketcan's while ``fail_send`` / ``fail_recv``."""

    def __init__(self, channel: str) -> None:
        self.inner = can.Bus(interface="virtual", channel=channel)
        self.fail_send = False
        self.fail_recv = False
        super().__init__(channel=channel)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if self.fail_send:
            raise can.CanOperationError("Transmit buffer full")
        self.inner.send(msg, timeout)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if self.fail_recv:
            raise can.CanOperationError("Error receiving: Network is down", 100)
        return self.inner.recv(timeout), True

    def shutdown(self) -> None:
        super().shutdown()
        self.inner.shutdown()


@pytest.fixture
def channel() -> str:
    return f"fb-buserr-{next(_channels)}-{time.monotonic_ns()}"


def _net(tmp_path: Path, channel: str, kind: str, map_file: Path, count: int) -> Path:
    f = tmp_path / f"{kind}.yaml"
    f.write_text(
        "cycle_time_us: 5000\nreceive_timeout_us: 20000\nsafe_stop_after: 10\nbuses:\n"
        f"  - {{name: bus, type: {kind}, interface: {channel}, can_interface: virtual,\n"
        f"     slaves: [{{name: 'n{{i}}', map: {json.dumps(str(map_file))}, node_id: 1, count: {count}}}]}}\n"
    )
    return f


@pytest.fixture
def canopen_nodes(channel: str) -> Iterator[CanopenSimulator]:
    drive = load_drive_map(DEMO_MAP)
    with (
        can.Bus(interface="virtual", channel=channel) as bus,
        CanopenSimulator(bus, [(drive, n) for n in (1, 2)], dt_s=0.005) as sim,
    ):
        yield sim
    assert not sim.errors


@pytest.fixture
def motors(channel: str) -> Iterator[MitMotorSimulator]:
    drive = load_drive_map(MIT_MAP)
    with (
        can.Bus(interface="virtual", channel=channel) as bus,
        MitMotorSimulator(bus, [(drive, n) for n in (1, 2)], dt_s=0.005) as sim,
    ):
        yield sim
    assert not sim.errors


def _fresh_within(op: Operational, cycles: int) -> bool:
    """Whether an exchange within ``cycles`` came back fresh: the emulator thread answers within the
    receive timeout on a quiet machine, not always on one loaded with four CPU burners."""
    return any(op.exchange().fresh for _ in range(cycles))


def _backend(kind: str, net_file: Path, **options: Any) -> Any:
    """The backend of the network's one bus, brought up by hand (no Network around it)."""
    b = backend_class(kind)(load_network(net_file).buses[0], **options)
    b.open()
    b.configure()
    b.safe_op()
    b.op()
    for _ in range(3):
        b.send()
        assert b.receive() == b.expected_wkc and b.arrived().all()
    return b


@pytest.mark.parametrize("kind", ["canopen", "rawcan"])
def test_a_transmit_error_is_a_bus_io_error_and_stop_and_close_do_not_raise(
    kind: str, channel: str, tmp_path: Path, request: pytest.FixtureRequest
) -> None:
    request.getfixturevalue("canopen_nodes" if kind == "canopen" else "motors")
    port = FailingBus(channel)
    try:
        map_file = DEMO_MAP if kind == "canopen" else MIT_MAP
        backend = _backend(kind, _net(tmp_path, channel, kind, map_file, 2), can_bus=port)
        port.fail_send = True
        with pytest.raises(
            BusIoError, match=r"cannot send on virtual channel .*: Transmit buffer full"
        ) as err:
            backend.send()
        assert isinstance(err.value.cause, can.CanOperationError) and err.value.__cause__ is err.value.cause
        assert (
            backend.tx_errors == 1 and backend.last_error == "send: CanOperationError: Transmit buffer full"
        )
        backend.stop()  # NMT pre-operational / exit motor mode on the dead bus: kept, not raised
        assert backend.tx_errors == 2 and backend.last_error.startswith(
            "stop: BusIoError: bus 'bus': cannot send"
        )
        backend.close()
        backend.close()  # idempotent
    finally:
        port.shutdown()


@pytest.mark.parametrize("kind", ["canopen", "rawcan"])
def test_a_receive_error_is_a_bus_io_error_and_no_node_arrived(
    kind: str, channel: str, tmp_path: Path, request: pytest.FixtureRequest
) -> None:
    request.getfixturevalue("canopen_nodes" if kind == "canopen" else "motors")
    port = FailingBus(channel)
    try:
        map_file = DEMO_MAP if kind == "canopen" else MIT_MAP
        backend = _backend(kind, _net(tmp_path, channel, kind, map_file, 2), can_bus=port)
        backend.send()
        port.fail_recv = True
        with pytest.raises(BusIoError, match="cannot receive on virtual channel") as err:
            backend.receive()
        assert isinstance(err.value.cause, can.CanOperationError)
        assert not backend.arrived().any() and backend.rx_errors == 1
        port.fail_recv = False
        backend.stop()
        backend.close()
    finally:
        port.shutdown()


def test_close_keeps_a_failing_shutdown_in_last_error(
    canopen_nodes: CanopenSimulator, channel: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The backend's own bus refuses to shut down: close() records it and still frees the channel."""
    net_file = _net(tmp_path, channel, "canopen", DEMO_MAP, 2)
    backend = _backend("canopen", net_file)
    port = backend._bus  # the python-can bus the backend opened itself

    def refuse() -> None:
        raise can.CanOperationError("Failed to close: device gone")

    monkeypatch.setattr(port, "shutdown", refuse)
    backend.stop()
    backend.close()
    assert backend.last_error == "close: CanOperationError: Failed to close: device gone"
    monkeypatch.undo()
    port.shutdown()
    with open_network(net_file) as again:  # the channel is free for the next master
        assert _fresh_within(again.bring_up(), 20)


def test_rawcan_counts_bus_off_and_never_takes_an_error_frame_for_a_reply(
    motors: MitMotorSimulator, channel: str, tmp_path: Path
) -> None:
    """While the cycle waits for silent motor 2, an error frame of class 0x002 (lost arbitration) comes,
    its data laid out like motor 2's reply: it is counted, never taken for the reply (nor as late)."""
    with (
        can.Bus(interface="virtual", channel=channel) as injector,
        open_network(_net(tmp_path, channel, "rawcan", MIT_MAP, 2)) as net,
    ):
        op = net.bring_up()
        backend = net.backends[0]
        assert _fresh_within(op, 20)
        motors.silence(2)
        injector.send(
            can.Message(arbitration_id=0x040, is_error_frame=True, is_extended_id=False, data=bytes(8))
        )
        st = op.exchange().buses[0]
        # a reported bus-off is a bus error (docs/safety.md S1): every motor stale, the safe stop latched
        assert list(st.fresh) == [False, False] and st.error is not None and "bus-off" in st.error
        assert st.safe_stop
        like_a_reply = bytes([2, 0x7F, 0xFF, 0x7F, 0xF7, 0xFF])
        frame = can.Message(
            arbitration_id=0x002, is_error_frame=True, is_extended_id=False, data=like_a_reply
        )
        timer = threading.Timer(
            0.005, injector.send, (frame,)
        )  # inside the 20 ms the cycle waits for motor 2
        timer.start()
        fresh = list(op.exchange().buses[0].fresh)  # (the result object is reused by the next cycle)
        timer.join()
        op.exchange()  # had it come after that cycle, it is taken from the queue now
        assert fresh == [True, False]
        assert backend.error_frames == 2 and backend.bus_off == 1 and backend.late_frames == 0
