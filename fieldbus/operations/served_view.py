"""``fieldbus monitor --dds``: a served bus seen from its DDS state and diagnostics alone (no bus access).

:class:`ServedView` joins the served namespace as a watcher through
:mod:`fieldbus.remote` (it never claims a group, so it commands nothing),
keeps each group's newest ``AxisState`` and the newest ``DiagnosticArray``,
and gives them as plain data (:meth:`ServedView.snapshot`) and as text
(:func:`render`). Freshness is the bus's own per-axis flag plus the age of the
newest state received (s, this process's clock).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic

from fieldbus.core.cia402 import State402
from fieldbus.dds import messages as m
from fieldbus.dds.gate import GateState
from fieldbus.dds.participant import DIAGNOSTICS, service_names
from fieldbus.remote import Remote

LEVELS = {0: "OK", 1: "WARN", 2: "ERROR", 3: "STALE"}


class ServedView:
    """A read-only watcher of the bus served under ``namespace``; use it from one thread."""

    def __init__(
        self,
        namespace: str,
        *,
        domain: int | None = None,
        interface: str | None = None,
        peers: Sequence[str] = (),
        timeout_s: float = 10.0,
    ) -> None:
        self.remote = Remote(
            namespace, domain=domain, interface=interface, peers=peers, deadline_s=0.2, timeout_s=timeout_s
        )
        dp = self.remote.participant.dp
        topic = Topic(dp, service_names(self.remote.namespace)["diagnostics"], m.DiagnosticArray)
        self._diag = DataReader(dp, topic, qos=DIAGNOSTICS)
        self.diagnostics: m.DiagnosticArray | None = None
        self._state_at = time.monotonic()  # Remote's constructor waited for a first state of every group

    def close(self) -> None:
        self.remote.close()

    def refresh(self, wait_s: float = 0.2) -> None:
        """Take the newest states (waiting at most ``wait_s`` for the next ones) and diagnostics."""
        res = self.remote.exchange(deadline_s=wait_s)
        if not res.late:
            self._state_at = time.monotonic()
        for d in self._diag.take(N=16):
            if isinstance(d, m.DiagnosticArray):
                self.diagnostics = d

    def wait_diagnostics(self, timeout_s: float) -> bool:
        """Refresh until a diagnostics message has come (the server publishes its newest to late joiners)."""
        end = time.monotonic() + timeout_s
        while self.diagnostics is None and time.monotonic() < end:
            self.refresh(wait_s=0.1)
        return self.diagnostics is not None

    def snapshot(self) -> dict[str, Any]:
        """What the view shows, as plain data (``--json``)."""
        now = time.monotonic()
        r = self.remote
        groups = []
        for name, g in r.groups.items():
            st = g.state
            pos = g.joint_state.get("position")
            vel = g.joint_state.get("velocity")
            eff = g.joint_state.get("effort")
            axes = []
            for i, axis in enumerate(g.axes):
                axes.append(
                    {
                        "name": axis,
                        "position": float(g.inputs.values[pos][i]) if pos else None,
                        "velocity": float(g.inputs.values[vel][i]) if vel else None,
                        "effort": float(g.inputs.values[eff][i]) if eff else None,
                        "fresh": bool(g.fresh[i]),
                        "drive_state": _state_name(int(g.drive_state[i])),
                    }
                )
            groups.append(
                {
                    "name": name,
                    "cycle": int(st.cycle),
                    "state_age_s": round(now - self._state_at, 3),
                    "gate": GateState(st.gate).name,
                    "owner": st.owner,
                    "command_sequence": int(st.command_sequence),
                    "command_age": int(st.command_age),
                    "safe_stop": bool(st.safe_stop),
                    "dropped_sequences": int(st.dropped_sequences),
                    "refused_commands": int(st.refused_commands),
                    "axes": axes,
                }
            )
        diag = None
        if self.diagnostics is not None:
            diag = [
                {
                    "name": s.name,
                    "level": LEVELS.get(int(s.level), str(s.level)),
                    "message": s.message,
                    "hardware_id": s.hardware_id,
                    "values": {kv.key: kv.value for kv in s.values},
                }
                for s in self.diagnostics.status
            ]
        return {
            "namespace": r.namespace,
            "domain": r.participant.domain_id,
            "cycle_time_us": r.cycle_time_us,
            "groups": groups,
            "diagnostics": diag,
            "diagnostics_age_s": _age_s(self.diagnostics.header.stamp)
            if self.diagnostics is not None
            else None,
        }


def _age_s(stamp: m.Time) -> float:
    """Seconds since ``stamp`` (the server's wall clock: exact on one host, as good as the clocks' sync across)."""
    return round(time.time() - stamp.sec - stamp.nanosec / 1e9, 3)


def _state_name(code: int) -> str:
    try:
        return State402(code).name.replace("_", " ").lower()
    except ValueError:
        return "-"


def _num(v: float | None) -> str:
    return f"{v:+.4f}" if v is not None else "-"


def render(snap: dict[str, Any]) -> str:
    """The view as text: per group its gate and joints, then each diagnostics status with its values."""
    lines = [
        f"served '{snap['namespace']}' on DDS domain {snap['domain']}, {snap['cycle_time_us']:g} us cycle"
    ]
    for g in snap["groups"]:
        stop = "  SAFE STOP" if g["safe_stop"] else ""
        lines.append(
            f"group {g['name']}: cycle {g['cycle']} (state {g['state_age_s'] * 1e3:.0f} ms old)  "
            f"gate {g['gate']}{stop}  owner {g['owner'] or '-'}  command #{g['command_sequence']} "
            f"age {g['command_age']} cycles  dropped {g['dropped_sequences']}  refused {g['refused_commands']}"
        )
        lines.append(f"  {'joint':<12} {'position':>10} {'velocity':>10} {'effort':>10}  inputs  drive state")
        for a in g["axes"]:
            lines.append(
                f"  {a['name']:<12} {_num(a['position']):>10} {_num(a['velocity']):>10} "
                f"{_num(a['effort']):>10}  {'fresh' if a['fresh'] else 'STALE':<6}  {a['drive_state']}"
            )
    diag = snap["diagnostics"]
    if diag is None:
        lines.append("diagnostics: none received yet")
    else:
        lines.append(f"diagnostics ({snap['diagnostics_age_s']:.1f} s old):")
        for s in diag:
            lines.append(f"  {s['name']} [{s['level']}] {s['message']}")
            values = "  ".join(f"{k}={v}" for k, v in s["values"].items() if v != "")
            if values:
                lines.append(f"    {values}")
    return "\n".join(lines)
