"""``fieldbus plot`` of real recordings, read from matplotlib's figure objects (titles, legend, line styles).

A soak on the sim backend with a power cycle records a safe stop, the recovery and the rest; it
measures no wake-up latency (``fieldbus report`` says "not measured"), and its generated network
file is a temporary file, gone once the soak ends.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from fieldbus.cli import main
from fieldbus.commands.demo import DEMO_MAP
from fieldbus.commands.plot import draw_recording, figure_size
from fieldbus.recording import load
from fieldbus.recording.summary import summary

pytestmark = pytest.mark.timeout(300)


def _figure(path: Path) -> Figure:
    rec = load(path)
    fig = Figure(figsize=figure_size(rec))
    draw_recording(fig, rec)
    return fig


def test_soak_plot_says_not_measured_tells_events_apart_and_names_no_temporary_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "soak.mcap"
    args = ["soak", "--demo", "--backend", "sim", "--axes", "2", "--cycles", "1500", "--seed", "1"]
    args += ["--faults", "loss=0.01,power_cycles=1", "--margin-us", "1e12", "--json", "--record", str(path)]
    assert main(args) == 0
    capsys.readouterr()
    rec = load(path)
    assert summary(rec)["latency_us"]["wakeup"]["cycles"] == 0  # what `report` prints as "not measured"
    fig = _figure(path)
    titles = [ax.get_title() for ax in fig.axes]
    assert "wake-up latency: not measured" in titles
    assert not any(t.startswith("wake-up latency: p50") for t in titles)

    events = fig.axes[-1]
    handles, labels = events.get_legend_handles_labels()
    styles = {}
    for h, label in zip(handles, labels, strict=True):
        assert isinstance(h, Line2D)
        if "misses" not in label:
            styles[label.rsplit(" (", 1)[0]] = (h.get_color(), h.get_linestyle())
    kinds = {e["kind"] for e in rec.events} - {"cia402_state"}
    assert {"safe_stop", "recovered"} <= kinds
    assert set(styles) == {k.replace("_", " ") for k in kinds}  # one legend entry per kind
    assert styles["safe stop"] != styles["recovered"]
    assert len(set(styles.values())) == len(styles)  # every kind its own colour and line style
    counts = {label.rsplit(" (", 1)[0]: label for label in labels}
    assert counts["safe stop"] == f"safe stop ({sum(e['kind'] == 'safe_stop' for e in rec.events)})"

    network = rec.meta["network"]
    assert not Path(network).exists()  # the soak's generated network: deleted
    assert fig.get_suptitle() == "soak.mcap"


def test_a_run_plot_names_the_users_network_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    net = tmp_path / "arm.yaml"
    net.write_text(
        "cycle_time_us: 1000\nbuses:\n  - {name: arm, type: ethercat, interface: sim,\n"
        f"     slaves: [{{name: 'a{{i}}', map: {json.dumps(str(DEMO_MAP))}, count: 2}}]}}\n"
    )
    path = tmp_path / "run.mcap"
    assert main(["run", str(net), "--backend", "sim", "--cycles", "200", "--record", str(path)]) in (0, 3)
    capsys.readouterr()
    fig = _figure(path)
    assert fig.get_suptitle() == "run.mcap: network arm.yaml"
    assert any(ax.get_title().startswith("wake-up latency: p50 ") for ax in fig.axes)  # measured here
