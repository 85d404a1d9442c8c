"""The served wheeled base (examples/amr_base.yaml) driven as Nav2 would: cmd_vel in, odom and tf out.

The client (tests/integration/dds/ros2_base_client.py) is written with cyclonedds and the standard ROS 2
message definitions only; it imports nothing of fieldbus. The served cycle runs in this process on the
emulator's virtual clock (local DDS delivery is synchronous: a sample written before a cycle is taken in
that cycle), so every bound is in cycles or virtual seconds. The ground truth is the emulated drives'
own shaft positions (``emu.drive_positions``), integrated here.
"""

from __future__ import annotations

import ast
import math
import os
import shutil
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("cyclonedds")

from fieldbus.dds.gate import Deadline
from fieldbus.dds.participant import Participant
from fieldbus.dds.server import BusServer, ServeOptions
from fieldbus.testing import emulate

sys.path.insert(0, str(Path(__file__).parent / "dds"))
from ros2_base_client import BaseClient

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
COUNTS_PER_RAD = 4096 * 20 / (2 * math.pi)  # seed 001: 4096 counts/rev encoder, 20:1 reduction
DOMAIN = 1 + (os.getpid() * 17 + 5) % 200


class Truth:
    """The base's pose from the emulated drives' shaft positions (1 ms steps, midpoint heading)."""

    def __init__(self, positions: list[float]) -> None:
        self.last = [p / COUNTS_PER_RAD for p in positions]
        self.x = self.y = self.heading = self.travel = 0.0

    def update(self, positions: list[float]) -> None:
        now = [p / COUNTS_PER_RAD for p in positions]
        dl, dr = ((n - o) * 0.08 for n, o in zip(now, self.last, strict=True))
        self.last = now
        ds, dth = (dl + dr) / 2, (dr - dl) / 0.45
        self.x += ds * math.cos(self.heading + dth / 2)
        self.y += ds * math.sin(self.heading + dth / 2)
        self.heading += dth
        self.travel += abs(ds)


class ServedBase:
    def __init__(self, emu: Any, server: BusServer) -> None:
        self.emu, self.server, self.k = emu, server, 0
        self.truth = Truth(emu.drive_positions("wheels"))

    def cycles(self, n: int, each: Any = None) -> None:
        for _ in range(n):
            if each is not None:
                each()
            self.server.step(self.k)
            self.k += 1
            self.truth.update(self.emu.drive_positions("wheels"))
            self.emu.clock.sleep(self.emu.cycle_time_us / 1e6)

    @property
    def speeds(self) -> list[float]:
        return [float(v) for v in self.emu.op["wheels"].inputs["velocity_actual_value"]]


@pytest.fixture
def served(tmp_path: Path) -> Iterator[ServedBase]:
    shutil.copytree(EXAMPLES / "maps", tmp_path / "maps")
    net = tmp_path / "amr_base.yaml"
    shutil.copy(EXAMPLES / "amr_base.yaml", net)
    with emulate(net, bring_up=False) as emu:
        server = BusServer(
            emu.network,
            Participant(DOMAIN, "lo"),
            ServeOptions("amr", deadline=Deadline(20, 200), publish_every=10, diagnostics_every=10**9),
            clock=emu.clock.now_ns,
        )
        server.attach(emu.bring_up())
        s = ServedBase(emu, server)
        s.cycles(20)
        yield s


def test_the_client_imports_nothing_of_fieldbus() -> None:
    tree = ast.parse((Path(__file__).parent / "dds" / "ros2_base_client.py").read_text())
    names = [a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names]
    names += [n.module or "" for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)]
    assert names and not [n for n in names if n.startswith(("fieldbus", "sim_slaves"))]


def _yaw(q: Any) -> float:
    return math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z))


def test_nav2_style_client_drives_a_2m_square_and_odometry_matches_the_drives(served: ServedBase) -> None:
    nav = BaseClient(DOMAIN)
    served.cycles(10)
    state = {"lin": 0.0, "ang": 0.0}

    def send() -> None:  # Nav2's controller server publishes cmd_vel at 20 Hz
        if served.k % 50 == 0:
            nav.send(state["lin"], state["ang"])

    nav.send(0.0, 0.0)  # takes the base: the drives enable, nothing moves
    served.cycles(400, send)
    assert served.truth.travel < 1e-6
    for side in range(4):
        state.update(lin=1.0, ang=0.0)
        served.cycles(2300, send)  # 1 s ramp to 1 m/s (0.5 m), 1.3 s at 1 m/s, 0.67 s down (0.33 m)
        state.update(lin=0.0)
        served.cycles(700, send)
        state.update(ang=1.0)
        goal = (side + 1) * math.pi / 2
        for _ in range(4000):
            nav.poll()
            if (
                nav.last_odom
                and abs(math.remainder(_yaw(nav.last_odom.pose.pose.orientation) - goal, math.tau)) < 0.02
            ):
                break
            served.cycles(1, send)
        state.update(ang=0.0)
        served.cycles(300, send)
    nav.poll()
    odo, truth = nav.last_odom, served.truth
    assert odo is not None and odo.header.frame_id == "odom" and odo.child_frame_id == "base_footprint"
    px, py = odo.pose.pose.position.x, odo.pose.pose.position.y
    assert truth.travel > 7.0
    assert math.hypot(px - truth.x, py - truth.y) <= 0.005 * truth.travel, (px, py, truth.x, truth.y)
    assert abs(math.remainder(_yaw(odo.pose.pose.orientation) - truth.heading, math.tau)) < 0.01
    assert odo.pose.covariance[35] == pytest.approx(0.01)  # the file's yaw variance
    tf = nav.last_tf
    assert tf is not None and tf.header.frame_id == "odom" and tf.child_frame_id == "base_footprint"
    assert tf.transform.translation.x == pytest.approx(px, abs=0.01)
    # the client stops: the base is at rest within the timeout plus the ramp from where it is (at rest here)
    state.update(lin=0.8, ang=0.0)
    served.cycles(1500, send)
    stop_at = served.k
    served.cycles(500 + 600 + 50)  # 0.5 s timeout + 0.8 m/s at 1.5 m/s^2 (0.53 s) + a margin
    assert max(abs(v) for v in served.speeds) < 0.05, served.speeds
    moved = served.truth.travel
    served.cycles(300)
    assert served.truth.travel - moved < 1e-3
    assert served.k - stop_at >= 1150


def test_an_over_limit_command_is_saturated_and_said_on_diagnostics(served: ServedBase) -> None:
    nav = BaseClient(DOMAIN)
    served.cycles(400, lambda: nav.send(0.0, 0.0) if served.k % 50 == 0 else None)
    served.cycles(2000, lambda: nav.send(3.0, 0.0) if served.k % 50 == 0 else None)
    nav.poll()
    warn = [
        s for s in nav.statuses if s.name == "fieldbus/base" and s.level == 1 and "saturated" in s.message
    ]
    assert warn, [(s.name, s.level, s.message) for s in nav.statuses]
    assert "velocity" in warn[0].message and "asked 3" in warn[0].message
    assert nav.last_odom is not None and nav.last_odom.twist.twist.linear.x == pytest.approx(1.5, abs=0.02)
    wheel = 1.5 / 0.08  # rad/s at the wheel at the limit
    assert max(served.speeds) <= wheel * 1.01


def test_nan_and_a_second_participant_are_refused_and_a_dead_owner_lets_go(served: ServedBase) -> None:
    nav = BaseClient(DOMAIN)
    served.cycles(400, lambda: nav.send(0.0, 0.0) if served.k % 50 == 0 else None)
    served.cycles(800, lambda: nav.send(0.5, 0.0) if served.k % 50 == 0 else None)
    base = served.server.base
    assert base is not None and base.owner is not None
    rogue = BaseClient(DOMAIN, stamped=True)
    served.cycles(200, lambda: (nav.send(0.5, 0.0), rogue.send(-1.0, 2.0)) if served.k % 50 == 0 else None)
    assert base.refusals["not_owner"] >= 4
    assert base.base is not None and base.base.last is not None and base.base.last.asked_angular == 0.0
    # NaN from the owner: refused, never liveness: the base times out and comes to rest
    served.cycles(1200, lambda: nav.send(math.nan, 0.0) if served.k % 50 == 0 else None)
    assert base.refusals["not_finite"] >= 23
    assert max(abs(v) for v in served.speeds) < 0.05
    # the owner dies: the base (at rest) lets go, and another participant takes it
    nav.cmd = None
    nav.dp = None
    import gc

    gc.collect()
    served.cycles(100)
    assert base.owner is None
    served.cycles(400, lambda: rogue.send(0.3, 0.0) if served.k % 50 == 0 else None)
    assert base.owner is not None
    served.cycles(800, lambda: rogue.send(0.3, 0.0) if served.k % 50 == 0 else None)
    assert min(served.speeds) > 0.3 / 0.08 * 0.9


def test_set_odometry_moves_the_odometry_not_the_base(served: ServedBase) -> None:
    import json

    from cyclonedds.domain import DomainParticipant
    from cyclonedds.pub import DataWriter
    from cyclonedds.sub import DataReader
    from cyclonedds.topic import Topic

    from fieldbus.dds import messages as m
    from fieldbus.dds.participant import RELIABLE

    nav = BaseClient(DOMAIN)
    dp = DomainParticipant(DOMAIN)
    req = DataWriter(dp, Topic(dp, "rt/amr/request", m.Request), qos=RELIABLE)
    rep = DataReader(dp, Topic(dp, "rt/amr/reply", m.Reply), qos=RELIABLE)
    served.cycles(30)
    for rid, arg in enumerate(({"x": 1.5, "y": -2.0, "yaw": 0.5}, {"x": float("nan")}), start=1):
        req.write(m.Request(client_id="op", request_id=rid, verb="set_odometry", argument=json.dumps(arg)))
        served.cycles(30)
        replies = [r for r in rep.take(N=8) if isinstance(r, m.Reply) and r.request_id == rid]
        assert replies and replies[0].ok == (rid == 1), replies
    served.cycles(30)
    nav.poll()
    odo = nav.last_odom
    assert odo is not None
    assert (odo.pose.pose.position.x, odo.pose.pose.position.y) == pytest.approx((1.5, -2.0))
    assert _yaw(odo.pose.pose.orientation) == pytest.approx(0.5)
    assert served.truth.travel < 1e-6  # nothing moved
