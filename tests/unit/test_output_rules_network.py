"""A network file's per-slave ``limits:`` narrow the map's output limits (never widen them)."""

from __future__ import annotations

import math
import struct
from pathlib import Path

import pytest

import fieldbus
from fieldbus.commands.demo import DEMO_MAP
from fieldbus.errors import PdoMapError

COUNTS_PER_RAD = 20860.7568  # demo_joint's target_position factor
WINDOW = (-41721, 62582)  # 0x607D:01..02 in counts: -2 rad .. 3 rad


def _map(tmp_path: Path) -> Path:
    """demo_joint with a software position limit 0x607D (-2..3 rad) written at start-up."""
    text = DEMO_MAP.read_text().replace(
        "sdo:\n",
        "sdo:\n"
        f"  - {{index: 0x607D, sub_index: 1, type: int32, value: {WINDOW[0]}}}\n"
        f"  - {{index: 0x607D, sub_index: 2, type: int32, value: {WINDOW[1]}}}\n",
        1,
    )
    f = tmp_path / "joint.yaml"
    f.write_text(text)
    return f


def _network(tmp_path: Path, slaves: str) -> Path:
    f = tmp_path / "net.yaml"
    f.write_text(
        "cycle_time_us: 1000\nreceive_timeout_us: 5000\nbuses:\n"
        "  - name: arm\n    type: ethercat\n    interface: sim0\n    slaves:\n" + slaves
    )
    return f


def test_a_slave_s_limits_narrow_its_rows_only_and_saturate_on_the_wire(tmp_path: Path) -> None:
    joint = _map(tmp_path)
    f = _network(
        tmp_path,
        f"      - {{name: j0, map: {joint}}}\n"
        f"      - {{name: j1, map: {joint}, limits: {{target_position: {{min: -1.0, max: 1.5}}}}}}\n"
        f"      - {{name: j2, map: {joint}, limits: {{target_position: {{max: 0.5, max_rate: 2.0}}}}}}\n",
    )
    slaves = fieldbus.load_network(f).buses[0].slaves
    assert slaves[0].limits == () and [lim.channel for lim in slaves[1].limits] == ["target_position"]
    with fieldbus.open_network(f, backend="sim") as net:
        op = net.bring_up()
        out = op["arm"].outputs
        out["target_position"][:] = [10.0, 10.0, -10.0]
        res = op.exchange()
        chain = net.backends[0].chain  # type: ignore[attr-defined]
        got = [struct.unpack_from("<Hi", esc.mem, esc.sm[2][0])[1] for esc in chain.slaves]
        # what each emulated ESC holds in its SM2 memory: j0 the map's 3 rad, j1 its own 1.5 rad, j2 -0.5
        assert got == [WINDOW[1], round(1.5 * COUNTS_PER_RAD), round(-0.5 * COUNTS_PER_RAD)], got
        clamps = {e.axis: e for e in res.events if isinstance(e, fieldbus.OutputClamp)}
        assert clamps[1].sent == pytest.approx(1.5) and clamps[2].sent == pytest.approx(-0.5)
        lim = {r: {c.channel: c for c in v} for r, v in op.output_rules["arm"].row_limits.items()}
        assert set(lim) == {1, 2}
        assert (lim[2]["target_position"].min, lim[2]["target_position"].max) == pytest.approx((-0.5, 0.5))
        assert lim[2]["target_position"].max_step == pytest.approx(0.002)  # 2 rad/s x 1 ms


@pytest.mark.parametrize(
    ("limits", "key", "why"),
    [
        (
            "{target_position: {min: -3.0, max: 1.0}}",
            "min",
            r"min -3 is below the map.s window -1\.99998\.\.2\.99999 \(0x607D\)",
        ),
        ("{target_position: {min: 0.0, max: 4.0}}", "max", r"max 4 is above the map's window"),
        ("{target_position: {max: 4.0}}", "max", r"min -4 is below the map's window"),  # max alone: -4..4
        ("{target_position: {min: 1.0, max: 0.5}}", "max", r"max 0\.5 must be greater than min 1"),
        ("{target_positon: {max: 1.0}}", "target_positon", r"did you mean"),
        ("{target_position: {max: -1.0}}", "max", r"give a positive max"),
    ],
)
def test_a_widening_or_bad_slave_limit_is_a_located_error(
    tmp_path: Path, limits: str, key: str, why: str
) -> None:
    joint = _map(tmp_path)
    f = _network(tmp_path, f"      - name: j0\n        map: {joint}\n        limits: {limits}\n")
    with pytest.raises(PdoMapError) as err:
        fieldbus.load_network(f)
    text = str(err.value)
    assert "net.yaml:10:" in text and key in text, text
    assert __import__("re").search(why, text), text


def test_a_step_wider_than_the_map_s_is_refused(tmp_path: Path) -> None:
    joint = tmp_path / "joint.yaml"
    joint.write_text(DEMO_MAP.read_text() + "limits:\n  target_position: {max_rate: 1.0}\n")
    f = _network(
        tmp_path,
        f"      - name: j0\n        map: {joint}\n        limits: {{target_position: {{max_step: 0.01}}}}\n",
    )
    with pytest.raises(
        PdoMapError, match=r"net\.yaml:10:.*max_step.*a step of 0\.01 per cycle is above the map's 0\.001"
    ):
        fieldbus.load_network(f)
    f = _network(
        tmp_path,
        f"      - name: j0\n        map: {joint}\n        limits: {{target_position: {{max_step: 0.0005}}}}\n",
    )
    (slave,) = fieldbus.load_network(f).buses[0].slaves
    assert slave.limits[0].max_step == 0.0005 and not math.isinf(slave.limits[0].max_step)
