"""What the plots say, read from matplotlib's figure objects (texts, line styles, order), not pixels.

``bandwidth --plot``: no two frame labels overlap, each sits inside its own bar or is named in the
legend; a raw-CAN bus shows each motor's command and then its reply, named so (not as CANopen
PDOs). A latency histogram with no cycle measured says "not measured", as ``fieldbus report`` does.
"""

from __future__ import annotations

import itertools
from pathlib import Path
from typing import Any

from matplotlib.figure import Figure

from fieldbus.commands.bandwidth import draw_cycles
from fieldbus.commands.cycleopts import draw_histogram
from fieldbus.core.bandwidth import (
    EcatSlave,
    EthercatParams,
    NetworkResult,
    ethercat_cycle,
    network_bandwidth,
)
from fieldbus.core.network import load_network, network_from_text
from fieldbus.platform.timing import LatencyHistogram

REPO = Path(__file__).resolve().parents[2]
MIT = REPO / "pdo_maps" / "cubemars_ak80_9_mit.yaml"


def _drawn(result: NetworkResult) -> tuple[Figure, Any, list[Any], list[str]]:
    fig = Figure()
    draw_cycles(fig, result)
    fig.canvas.draw()  # the final layout, as saved
    (ax,) = fig.axes
    legend = [t.get_text() for lg in fig.legends for t in lg.get_texts()]
    return fig, ax, list(ax.texts), legend


def _check_labels(result: NetworkResult) -> None:
    fig, ax, texts, legend = _drawn(result)
    renderer = fig.canvas.get_renderer()  # type: ignore[attr-defined]
    boxes = [t.get_window_extent(renderer) for t in texts]
    for (a, ta), (b, tb) in itertools.combinations(zip(boxes, texts, strict=True), 2):
        assert not a.overlaps(b), f"{ta.get_text()!r} overlaps {tb.get_text()!r}"
    bars = {
        (row, s.label): s for row, bus in enumerate(result.buses) for s in bus.timeline if s.duration_us > 0
    }
    named = set()
    for box, t in zip(boxes, texts, strict=True):
        _, row = t.get_position()
        s = bars[(round(row), t.get_text())]
        left, right = (ax.transData.transform((u, 0))[0] for u in (s.start_us, s.start_us + s.duration_us))
        assert left <= box.x0 and box.x1 <= right, f"{t.get_text()!r} leaves its bar"
        named.add((round(row), t.get_text()))
    for row, bus in enumerate(result.buses):
        for s in bus.timeline:
            if s.duration_us > 0 and (row, s.label) not in named:
                assert any(entry.startswith(f"{bus.name}: {s.label} (") for entry in legend), s.label


def test_ethercat_frame_labels_never_overlap() -> None:
    # 40 slaves of 200 + 200 bytes with separate write and read datagrams and DC: 11 frames of which
    # "frame 11" is short, and the forwarding time after them
    bus = ethercat_cycle(
        [EcatSlave(200, 200)] * 40, EthercatParams(mode="lrd_lwr", dc=True), 1000.0, name="b"
    )
    small = ethercat_cycle([EcatSlave(8, 8)] * 6, EthercatParams(dc=True), 1000.0, name="arm")
    _check_labels(NetworkResult(1000.0, (bus, small)))


def test_can_frame_labels_never_overlap() -> None:
    net = load_network(REPO / "examples" / "humanoid_can.yaml")
    _check_labels(network_bandwidth(net))


def _motors(count: int) -> NetworkResult:
    text = (
        "cycle_time_us: 1000\nbuses:\n  - {name: legs, type: rawcan, interface: can0, can_interface: virtual,\n"
        f"     slaves: [{{name: 'm{{i}}', map: {MIT}, node_id: 1, count: {count}}}]}}\n"
    )
    return network_bandwidth(network_from_text(text, "motors.yaml", REPO))


def test_raw_can_chart_shows_each_command_then_its_reply() -> None:
    (bus,) = _motors(3).buses
    labels = [s.label for s in bus.timeline]
    assert labels == ["m0 command", "m0 reply", "m1 command", "m1 reply", "m2 command", "m2 reply"]
    starts = [s.start_us for s in bus.timeline]
    assert starts == sorted(starts)
    _, _, texts, legend = _drawn(_motors(3))
    shown = [t.get_text() for t in texts] + legend
    assert not any("PDO" in s for s in shown)
    assert sum("command" in s for s in shown) == 3 and sum("reply" in s for s in shown) == 3


def test_an_empty_latency_histogram_says_not_measured() -> None:
    fig = Figure()
    ax = fig.add_subplot()
    draw_histogram(ax, "wake-up latency", LatencyHistogram(100))
    assert ax.get_title() == "wake-up latency: not measured"
    assert [t.get_text() for t in ax.texts] == ["not measured"]
    measured = LatencyHistogram(100)
    measured.add(12_000)
    ax2 = fig.add_subplot()
    draw_histogram(ax2, "wake-up latency", measured)
    assert ax2.get_title().startswith("wake-up latency: p50 ") and not ax2.texts


def test_a_histogram_with_a_duration_beyond_its_last_bin_draws() -> None:
    """A 140 ms exchange on a loaded host lands in the last bin (max_us and over): drawn, not a size error."""
    hist = LatencyHistogram(100)
    hist.add(50_000)
    hist.add(140_000_000)
    ax = Figure().add_subplot()
    draw_histogram(ax, "exchange() time", hist)
    assert ax.get_title().startswith("exchange() time: p50 ") and len(ax.patches) == 1
