"""What one cycle of the in-process EtherCAT path copies and allocates on the master's side.

The path: the image's wire bytes, SOEM's IO map, the LRW frame the emulated
chain processes, and back. A counting transport (the chain behind a proxy that
records each process-data frame it is handed) shows which buffer the chain gets
and what it holds at that moment; tracemalloc shows what a cycle allocates.
Pinned: outputs reach the frame in one copy (image -> frame: the IO map *is*
the frame's LRW data), inputs leave it in one copy (frame -> receive rows), no
buffer of the image's size is allocated per cycle, and the chain processes the
frame between ``send()`` and ``receive()`` as a wire would, not inside ``send()``.
Our master against our own emulator: the chain here is only the wire.
"""

from __future__ import annotations

import tracemalloc
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from fieldbus.commands.demo import DEMO_MAP
from fieldbus.network import Network, open_network
from fieldbus.testing import VirtualClock

pytest.importorskip("pysoem")

AXES = 40  # 22 bytes of process data each: an image copy (880 bytes) stands out from small objects
RECEIVE_TIMEOUT_US = 1000


class CountingChain:
    """The emulated chain behind a proxy: every process-data frame it processes is recorded as
    (buffer, its LRW data as the chain got them); ``loopback``: such frames are not processed, their
    working counter is set to ``loopback`` (nothing of the emulator runs, so nothing of it allocates)."""

    def __init__(self, chain: Any, data_at: int, data_size: int) -> None:
        self._chain = chain
        self._at, self._size = data_at, data_size
        self.seen: list[tuple[Any, bytes]] = []
        self.loopback: int | None = None

    def __getattr__(self, name: str) -> Any:
        return getattr(self._chain, name)

    def process_into(self, buf: Any, n: int, now_ns: int, **kw: Any) -> int:
        if self.loopback is None:
            self.seen.append((buf, bytes(buf[self._at : self._at + self._size])))
            got: int = self._chain.process_into(buf, n, now_ns, **kw)
            return got
        wkc_at = self._at + self._size
        buf[wkc_at], buf[wkc_at + 1] = self.loopback & 0xFF, self.loopback >> 8
        return n


@pytest.fixture
def net(tmp_path: Path) -> Iterator[Network]:
    f = tmp_path / "net.yaml"
    f.write_text(
        f"cycle_time_us: 1000\nreceive_timeout_us: {RECEIVE_TIMEOUT_US}\nbuses:\n"
        f"  - {{name: bus, type: ethercat, interface: none0, slaves: [{{name: 'j{{i}}', map: '{DEMO_MAP}', "
        f"count: {AXES}}}]}}\n"
    )
    with open_network(f, backend="sim", clock=VirtualClock()) as network:
        network.bring_up()
        yield network


def _counting(net: Network) -> tuple[Any, CountingChain]:
    backend: Any = net.backends[0]
    size = backend.out_bytes + sum(a.in_size for a in backend.areas)
    proxy = CountingChain(backend.master.chain, 14 + 2 + 10, size)  # Ethernet, EtherCAT, LRW headers
    backend.master.chain = proxy
    return backend, proxy


def test_outputs_reach_the_frame_in_one_copy_and_inputs_leave_it_in_one(net: Network) -> None:
    backend, proxy = _counting(net)
    wire = backend.groups[0].image.outputs.wire
    marker = np.arange(wire.size, dtype=np.uint64).astype(np.uint8).reshape(wire.shape) ^ 0x5A
    for cycle in range(3):
        np.copyto(wire, marker ^ cycle)  # as to_wire() leaves them (the encode is the network's)
        backend.send()
        assert not proxy.seen, "the chain ran inside send(): a wire processes the frame after it"
        wkc = backend.receive()
        assert wkc == backend.expected_wkc
        ((buf, data),), proxy.seen = proxy.seen, []
        # the frame the chain got carried the outputs, and its buffer is the IO map (no copy between)
        assert data[: wire.size] == (marker ^ cycle).tobytes()
        assert np.shares_memory(backend.master.iomap, np.frombuffer(buf, np.uint8))
        # counted: one copy per direction between the image's bytes and that frame
        assert [
            (np.shares_memory(d, np.frombuffer(buf, np.uint8)), s is wire) for d, s in backend._out_copies
        ] == [(True, True)]
        assert [
            (np.shares_memory(s, np.frombuffer(buf, np.uint8)), d is backend.rx[0])
            for d, s in backend._in_copies
        ] == [(True, True)]
        # what the chain wrote into the frame is in the receive rows
        frame_inputs = np.frombuffer(buf, np.uint8, backend.rx[0].size, 26 + backend.out_bytes)
        assert backend.rx[0].tobytes() == frame_inputs.tobytes()


def test_a_cycle_allocates_no_buffer_of_the_image_size(net: Network) -> None:
    """tracemalloc's peak over send() + receive() on a loopback wire: the cycle's own allocations."""
    backend, proxy = _counting(net)
    proxy.loopback = backend.expected_wkc
    image_bytes = backend.master.iomap.size
    for _ in range(20):
        backend.send()
        backend.receive()
    tracemalloc.start()
    try:
        peaks = []
        for _ in range(50):
            tracemalloc.reset_peak()
            base = tracemalloc.get_traced_memory()[0]
            backend.send()
            assert backend.receive() == backend.expected_wkc
            peaks.append(tracemalloc.get_traced_memory()[1] - base)
    finally:
        tracemalloc.stop()
    assert max(peaks) < image_bytes, (max(peaks), image_bytes)


def test_a_late_reply_in_the_frame_is_not_taken(net: Network) -> None:
    """The IO map is the frame: a reply held back past the timeout writes the frame's inputs, but the
    receive says lost (-1 -> None) and the receive rows keep their bytes (S2)."""
    backend: Any = net.backends[0]
    backend.send()
    assert backend.receive() == backend.expected_wkc
    chain, iomap = backend.master.chain, backend.master.iomap
    backend.rx[0][:] = 0xA5  # not what any slave sends: taken from the frame, it would be overwritten
    backend.delay_cycles(2 * RECEIVE_TIMEOUT_US / 1e6, 1)
    frames = chain.frames
    backend.send()
    assert chain.frames == frames  # sent, on its way: not processed yet
    assert backend.receive() is None
    assert chain.frames == frames + 1
    assert (iomap[backend.out_bytes :] != 0xA5).any()  # the late reply is in the frame
    assert (backend.rx[0] == 0xA5).all()  # and not in the receive rows
    backend.send()
    assert backend.receive() == backend.expected_wkc  # the next one in time is taken again
    assert backend.rx[0].tobytes() == iomap[backend.out_bytes :].tobytes()


def test_an_image_over_two_frames_goes_through_both(tmp_path: Path) -> None:
    """70 axes, 1540 bytes: two LRW frames (at most 1486 data bytes each); the IO map is then a buffer
    of its own, each frame's part copied in before the send and its inputs out after the reply."""
    f = tmp_path / "big.yaml"
    f.write_text(
        f"cycle_time_us: 1000\nreceive_timeout_us: {RECEIVE_TIMEOUT_US}\nbuses:\n"
        f"  - {{name: bus, type: ethercat, interface: none0, slaves: [{{name: 'j{{i}}', map: '{DEMO_MAP}', "
        "count: 70}]}\n"
    )
    with open_network(f, backend="sim", clock=VirtualClock()) as big:
        big.bring_up()
        backend: Any = big.backends[0]
        master = backend.master
        assert len(master._frames) == 2 and master.iomap.size == 1540
        seen: list[bytes] = []
        process = master.chain.process_into

        def counted(buf: Any, n: int, now_ns: int, **kw: Any) -> int:
            got: int = process(buf, n, now_ns, **kw)
            seen.append(bytes(buf[:n]))
            return got

        master.chain.process_into = counted
        wire = backend.groups[0].image.outputs.wire
        marker = (np.arange(wire.size) % 251).astype(np.uint8).reshape(wire.shape)
        np.copyto(wire, marker)
        backend.send()
        assert backend.receive() == backend.expected_wkc == 3 * 70
        assert len(seen) == 2
        lrw = [frame[26 : 26 + fr.hi - fr.lo] for frame, fr in zip(seen, master._frames, strict=True)]
        image = b"".join(lrw)
        assert image[: wire.size] == marker.tobytes()  # every output byte went out, in order
        assert backend.rx[0].tobytes() == image[backend.out_bytes :]  # every input byte came back
