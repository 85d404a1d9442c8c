"""A clean cycle skips the steps that have nothing to do, and a miss still gets every one of them.

Counted on a real sim network (the ethercat backend on the emulated chain, virtual clock): the backend's
``recover_step`` and ``diag_step`` are wrapped to count their calls. A clean cycle (fresh, not
recovering, no SDO queued, no error watch) calls neither; a lost frame gets its recovery steps in the
cycles after it and the status reports them; with an error watch the diagnostic read runs every free
cycle. Our master against our own emulator.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from fieldbus.commands.demo import DEMO_MAP
from fieldbus.network import Network, Operational, open_network
from fieldbus.testing import VirtualClock

pytest.importorskip("pysoem")


def _net(tmp_path: Path, **options: Any) -> Iterator[tuple[Network, Operational]]:
    f = tmp_path / "net.yaml"
    f.write_text(
        "cycle_time_us: 1000\nreceive_timeout_us: 1000\nbuses:\n"
        f"  - {{name: bus, type: ethercat, interface: none0, slaves: [{{name: 'j{{i}}', map: '{DEMO_MAP}', "
        "count: 3}]}\n"
    )
    with open_network(f, backend="sim", clock=VirtualClock(), **options) as network:
        yield network, network.bring_up()


@pytest.fixture
def net(tmp_path: Path) -> Iterator[tuple[Network, Operational]]:
    yield from _net(tmp_path)


def _count(backend: Any, name: str) -> list[int]:
    calls = [0]
    real = getattr(backend, name)

    def counted(*a: Any, **k: Any) -> Any:
        calls[0] += 1
        return real(*a, **k)

    setattr(backend, name, counted)
    return calls


def test_a_clean_cycle_calls_no_recovery_step_and_no_diagnostic_read(
    net: tuple[Network, Operational],
) -> None:
    network, op = net
    b: Any = network.backends[0]
    steps, diags = _count(b, "recover_step"), _count(b, "diag_step")
    for _ in range(50):
        assert op.exchange().fresh
    assert (steps[0], diags[0]) == (0, 0)  # before: a diag_step call every cycle (it found no watch)


def test_a_lost_frame_still_gets_its_recovery_steps_and_status(net: tuple[Network, Operational]) -> None:
    network, op = net
    b: Any = network.backends[0]
    steps = _count(b, "recover_step")
    st = op.result.bus("bus")
    b.chain.drop_frames(1, process_data=True)
    assert not op.exchange().fresh
    assert (
        steps[0] >= 1 and st.consecutive_misses == 1
    )  # the miss's cycle: a step (it waits for the next LRW)
    for _ in range(20):
        op.exchange()
    assert op.result.fresh and not st.recovering and not b.recovering
    assert st.recoveries == b.recoveries and st.recovery_error == b.last_recovery_error
    before = steps[0]
    for _ in range(20):
        assert op.exchange().fresh
    assert steps[0] == before  # clean again: no more steps


def test_with_an_error_watch_the_diagnostic_read_runs_every_free_cycle(tmp_path: Path) -> None:
    for network, op in _net(tmp_path, error_counters=True):
        assert network.backends[0].error_watch is not None
        diags = _count(network.backends[0], "diag_step")
        for _ in range(30):
            assert op.exchange().fresh
        assert diags[0] == 30
