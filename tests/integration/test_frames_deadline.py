"""The declarative family's feedback deadline (``feedback: {deadline_us: ...}``): a feedback frame that comes
later than that after the cycle's commands is stale (counted late, the motor's inputs held), one that
comes sooner is fresh; the bus's receive time-out alone would take both.

The real raw-CAN backend on python-can's virtual bus, on a virtual clock: this test's responder moves the
clock by the motor's answer time, then answers (time is judged on the clock, never the machine's). No
oracle for a made-up protocol: the responder is ours, what is judged is the backend's deadline.
"""

from __future__ import annotations

import itertools
import os
from pathlib import Path

import pytest

can = pytest.importorskip("can")

from fieldbus.core.pdo import load_drive_map  # noqa: E402
from fieldbus.errors import PdoMapError  # noqa: E402
from fieldbus.network import open_network  # noqa: E402
from fieldbus.platform.clock import VirtualClock  # noqa: E402

_channels = itertools.count()
MAP = """\
name: slow_wheel
rawcan:
  family: frames
  command:  {{id: 0x210, fields: [{{name: velocity, type: int, bits: 16, safe_value: 0}}]}}
  feedback: {{id: 0x290, {deadline}fields: [{{name: position, type: int, bits: 16}}]}}
"""


class _Responder(can.Listener):
    """Answers each command on 0x211 after ``delay_ns`` of the clock: position = the command's raw value."""

    def __init__(self, bus: can.BusABC, clock: VirtualClock) -> None:
        self.bus, self.clock, self.delay_ns = bus, clock, 0

    def on_message_received(self, msg: can.Message) -> None:
        if msg.arbitration_id == 0x211 and len(msg.data) == 2:
            self.clock.advance(self.delay_ns)  # the motor takes this long to answer
            self.bus.send(can.Message(arbitration_id=0x291, data=bytes(msg.data), is_extended_id=False))


def _network(tmp_path: Path, deadline: str) -> tuple[Path, str]:
    drive = tmp_path / "slow_wheel.yaml"
    drive.write_text(MAP.format(deadline=deadline))
    channel = f"fb-deadline-{os.getpid()}-{next(_channels)}"
    net = tmp_path / "net.yaml"
    net.write_text(
        "cycle_time_us: 10000\nreceive_timeout_us: 50000\nsafe_stop_after: 100\nbuses:\n"
        f"  - {{name: b, type: rawcan, interface: {channel}, can_interface: virtual,\n"
        f"     slaves: [{{name: w, map: '{drive}', node_id: 1}}]}}\n"
    )
    return net, channel


def _run(tmp_path: Path, deadline: str, delays_us: list[int]) -> tuple[list[bool], list[int], int]:
    """One cycle per delay (the command = the cycle's index): freshness, the position read, late frames."""
    net_file, channel = _network(tmp_path, deadline)
    clock = VirtualClock()
    fresh, read = [], []
    with can.Bus(interface="virtual", channel=channel, receive_own_messages=False) as sim_bus:
        motor = _Responder(sim_bus, clock)
        notifier = can.Notifier(sim_bus, [motor])
        try:
            with open_network(net_file, clock=clock) as net:
                op = net.bring_up()
                for k, delay in enumerate(delays_us, start=1):
                    motor.delay_ns = delay * 1000
                    op["b"].outputs["velocity"][0] = k
                    fresh.append(bool(op.exchange().fresh))
                    read.append(int(op["b"].inputs["position"][0]))
                op.exchange()  # drains what came after its cycle
                late = net.backend("b").late_frames
        finally:
            notifier.stop()
    return fresh, read, late


def test_a_feedback_frame_after_its_deadline_reads_stale_and_before_it_fresh(tmp_path: Path) -> None:
    fresh, read, late = _run(tmp_path, "deadline_us: 2000, ", [500, 3000, 1500, 2500, 0])
    assert fresh == [True, False, True, False, True]
    assert read == [1, 1, 3, 3, 5]  # a stale cycle holds the last fresh position
    assert late == 2


def test_without_a_deadline_the_receive_time_out_judges(tmp_path: Path) -> None:
    fresh, read, late = _run(tmp_path, "", [500, 3000, 1500])
    assert fresh == [True, True, True] and read == [1, 2, 3] and late == 0


@pytest.mark.parametrize(
    ("deadline", "where", "message"),
    [
        ("deadline_us: 0, ", "feedback.deadline_us", "finite time > 0"),
        ("deadline_us: -5, ", "feedback.deadline_us", "finite time > 0"),
        ("deadline_us: .nan, ", "feedback.deadline_us", "finite"),
        ("deadline_us: soon, ", "feedback.deadline_us", ""),
    ],
)
def test_a_bad_deadline_is_a_located_error(tmp_path: Path, deadline: str, where: str, message: str) -> None:
    drive = tmp_path / "slow_wheel.yaml"
    drive.write_text(MAP.format(deadline=deadline))
    with pytest.raises(PdoMapError) as err:
        load_drive_map(drive)
    text = str(err.value)
    assert "slow_wheel.yaml:5" in text and where in text and message in text


def test_a_deadline_on_the_command_frame_is_refused_naming_it(tmp_path: Path) -> None:
    drive = tmp_path / "slow_wheel.yaml"
    drive.write_text(MAP.format(deadline="").replace("{id: 0x210, ", "{id: 0x210, deadline_us: 10, "))
    with pytest.raises(PdoMapError, match=r"slow_wheel\.yaml:4.*command\.deadline_us.*feedback frame"):
        load_drive_map(drive)
