"""EMCY events in a recording: counted by the backend, never by the length of its bounded list.

CANopen backend and emulated nodes on python-can's virtual bus. The backend keeps at
most MAX_EMERGENCIES messages (it drops the older half when full); the recording must
still see every new one.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest

can = pytest.importorskip("can")
pytest.importorskip("mcap")

from fieldbus.backends import canopen as canopen_backend  # noqa: E402
from fieldbus.commands.demo import DEMO_MAP  # noqa: E402
from fieldbus.core.pdo import load_drive_map  # noqa: E402
from fieldbus.network import open_network  # noqa: E402
from fieldbus.recording import load  # noqa: E402
from sim_slaves.canopen import CanopenSimulator  # noqa: E402

pytestmark = pytest.mark.timeout(120)
OVER_CURRENT = 0x2310


def test_every_emcy_is_an_event_even_when_the_backend_trims_its_list(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(canopen_backend, "MAX_EMERGENCIES", 4)  # trims at 4, keeps 2
    channel = f"fb-rec-emcy-{time.monotonic_ns()}"
    net_file = tmp_path / "net.yaml"
    net_file.write_text(
        "cycle_time_us: 5000\nreceive_timeout_us: 20000\nsafe_stop_after: 1000\nbuses:\n"
        f"  - {{name: arm, type: canopen, interface: {channel}, can_interface: virtual,\n"
        f"     slaves: [{{name: 'a{{i}}', map: {json.dumps(str(DEMO_MAP))}, node_id: 1, count: 2}}]}}\n"
    )
    drive = load_drive_map(DEMO_MAP)
    sent_at: list[int] = []
    with (
        can.Bus(interface="virtual", channel=channel) as bus,
        CanopenSimulator(bus, [(drive, n) for n in (1, 2)], dt_s=0.005) as sim,
        open_network(net_file) as net,
    ):
        op = net.bring_up()
        op.record(tmp_path / "r.mcap", block_cycles=16, ring_blocks=64)  # 5 s: no drop on a busy CI
        for k in range(200):
            if k % 20 == 10:
                sim.send_emergency(2, OVER_CURRENT)
                sent_at.append(op.result.cycle)
            op.exchange()
        backend = net.backends[0]
        for _ in range(50):  # the last one may still be crossing the virtual bus's thread
            if backend.emcy_count == len(sent_at):
                break
            op.exchange()
        op.exchange()  # the cycle that sees it records it
        assert backend.emcy_count == len(sent_at) == 10
        assert len(backend.emergencies) < 10  # trimmed: its length is no count
    rec = load(tmp_path / "r.mcap")
    assert rec.dropped_blocks == 0
    emcys = [e for e in rec.events if e["kind"] == "emcy"]
    assert sum(e["new"] - e["old"] for e in emcys) == 10
    assert all("over-current" in e["detail"] for e in emcys)
    # each shows up within a few cycles of being sent (the frame crosses the virtual bus's thread)
    for at, e in zip(sent_at, emcys, strict=True):
        assert at <= e["cycle"] <= at + 5, (at, e)
