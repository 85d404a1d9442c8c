"""Fuzzing CAN: random frames into the emulated CANopen node and the CANopen backend's receive path.

No crash, no hang: the node answers, ignores, or aborts an SDO; the backend
ignores what it does not expect and never calls a node fresh from a frame of
the wrong length. CI runs 2,000 cases per test (``FIELDBUS_FUZZ_EXAMPLES``).
"""

from __future__ import annotations

import os
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

can = pytest.importorskip("can")

from fieldbus.commands.demo import DEMO_MAP  # noqa: E402
from fieldbus.core.pdo import load_drive_map  # noqa: E402
from sim_slaves.canopen import CanopenNode  # noqa: E402
from sim_slaves.canopen.simulator import CanopenSimulator  # noqa: E402

EXAMPLES = int(os.environ.get("FIELDBUS_FUZZ_EXAMPLES", "2000"))
SETTINGS = settings(max_examples=EXAMPLES, deadline=None, suppress_health_check=list(HealthCheck))
DRIVE = load_drive_map(DEMO_MAP)
FRAMES = st.lists(
    st.tuples(
        st.one_of(st.integers(0, 0x7FF), st.sampled_from([0x000, 0x080, 0x203, 0x303, 0x603, 0x703, 0x083])),
        st.binary(min_size=0, max_size=8),
    ),
    min_size=1,
    max_size=30,
)


class _NullBus:
    """Collects what the simulator sends (no thread, no python-can bus)."""

    def __init__(self) -> None:
        self.sent: list[Any] = []

    def send(self, msg: Any) -> None:
        assert len(msg.data) <= 8 and 0 <= msg.arbitration_id <= 0x7FF
        self.sent.append(msg)


@SETTINGS
@given(FRAMES)
def test_random_frames_into_the_emulated_nodes(frames: list[tuple[int, bytes]]) -> None:
    bus = _NullBus()
    sim = CanopenSimulator(bus, [(DRIVE, 3), (DRIVE, 4)], dt_s=0.001)  # type: ignore[arg-type]
    for n in sim.nodes.values():
        n.boot()
    for cob, data in frames:
        sim.handle(cob, data)  # must not raise
    for node in sim.nodes.values():
        node.sync(0.001)  # and the nodes still run


@SETTINGS
@given(st.binary(min_size=0, max_size=8), st.sampled_from([0, 1, 2, 3, 4, 5, 7]))
def test_random_sdo_requests_get_an_answer_or_nothing(data: bytes, ccs: int) -> None:
    node = CanopenNode(DRIVE, 5)
    node.boot()
    req = (bytes([ccs << 5 | (data[0] & 0x1F if data else 0)]) + data[1:]).ljust(8, b"\0")[:8]
    out = node.sdo(req)
    assert out is None or (out[0] == 0x585 and len(out[1]) == 8)


class _FeedBus:
    """A python-can stand-in whose recv() hands out the given frames, then None (the timeout)."""

    def __init__(self, frames: list[tuple[int, bytes]]) -> None:
        self.frames = [can.Message(arbitration_id=c, data=d, is_extended_id=False) for c, d in frames]
        self.sent: list[Any] = []

    def recv(self, timeout: float | None = None) -> Any:
        return self.frames.pop(0) if self.frames else None

    def send(self, msg: Any) -> None:
        self.sent.append(msg)


@SETTINGS
@given(FRAMES)
def test_random_frames_into_the_backend_receive_path(frames: list[tuple[int, bytes]]) -> None:
    from fieldbus.backends.canopen import CanopenBackend
    from fieldbus.core.network import network_from_text

    net = network_from_text(
        "cycle_time_us: 1000\nreceive_timeout_us: 1000\nbuses:\n"
        "  - {name: b, type: canopen, interface: x, can_interface: virtual,\n"
        f"     slaves: [{{name: 'j{{i}}', map: '{DEMO_MAP}', node_id: 3, count: 2}}]}}\n",
        "fuzz.yaml",
    )
    backend = CanopenBackend(net.buses[0], can_bus=_FeedBus(frames))
    backend.safe_op()  # the frame tables; no node is needed for the receive path
    backend._operational = True
    got = backend.receive()  # (send() would drain them as late TPDOs of an earlier SYNC)
    assert got is None or 1 <= got <= backend.expected_wkc
    arrived = backend.arrived()
    # a node is complete only if both its TPDOs came with the right length
    good = {(c, len(d)) for c, d in frames}
    for i, node in enumerate((3, 4)):
        if arrived[i]:
            assert (0x180 + node, 6) in good and (0x280 + node, 7) in good
    assert len(backend.emergencies) <= 1000
