"""``fieldbus serve NETWORK.yaml``: run a network's cycle and serve it over Cyclone DDS (ROS 2 names).

Per axis group, every cycle (or every n-th): ``sensor_msgs/JointState`` on
``rt/<namespace>/<group>/joint_states`` and ``fieldbus_msgs/AxisState`` on
``.../axis_state``; commands (``fieldbus_msgs/JointCommand``) from ``.../command``.
Requests (claim, release, enable, disable, clear_safe_stop, describe) on
``rt/<namespace>/request``, answers on ``rt/<namespace>/reply``; the same requests
as ROS 2 services ``/<namespace>/<group>/<name>`` (std_srvs Trigger / SetBool,
fieldbus_msgs SetMode / SdoRead / SdoWrite); diagnostics
(``diagnostic_msgs/DiagnosticArray``) on ``rt/<namespace>/diagnostics``. A network
file with a ``base:`` section is also a wheeled base in standard messages:
``cmd_vel`` in, ``odom``, ``tf``, ``joint_states`` and ``diagnostics`` out (docs/amr.md).
``fieldbus monitor --dds`` shows a served bus live.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
from types import FrameType
from typing import TYPE_CHECKING, Any

from fieldbus.commands import cycleopts
from fieldbus.commands.usage import epilog

if TYPE_CHECKING:
    from fieldbus.dds.server import BusServer, ServeOptions
    from fieldbus.platform.rt import RtState

HELP_EPILOG = """DDS domain and network interface:
  --domain N      the DDS domain id; default $ROS_DOMAIN_ID (as ROS 2 does), else 0
  --interface IF  the one network interface DDS uses (e.g. eth0); 'lo' also turns multicast off and
                  discovers peers by unicast on 127.0.0.1 (loopback has no multicast). Without it,
                  Cyclone DDS chooses, and $CYCLONEDDS_URI (XML text or file) configures it as usual.
  --peer ADDR     a unicast discovery peer (repeat it); for networks without multicast

command safety (cycles of this bus):
  no new command for --hold-after cycles: HOLD (the last command stays applied);
  for --stop-after cycles: SAFE STOP (the group's safe outputs), latched until the owner sends
  clear_safe_stop; an owner that sends no command after its claim, clear or enable latches the same
  way. One client owns a group (claim), known by its DDS participant: commands from any other
  participant are refused, whatever client_id they name, and so are NaN/inf and wrong lengths (each
  reason counted in the diagnostics). A sequence number that does not increase is dropped and counted.
  The bus's safe stop and a drive fault latch too; after clear_safe_stop the drives stay disabled
  until enable, and while no command applies the targets hold the joints (velocity, torque 0).

ROS 2 services, per group: /NS/GROUP/claim (std_srvs/SetBool), enable, disable, clear_safe_stop,
  home (std_srvs/Trigger), set_mode, sdo_read, sdo_write (fieldbus_msgs); see docs/dds.md.
  'fieldbus monitor --dds --namespace NS' shows the served bus live.

real time: the cycle thread sleeps to an absolute time --spin-us before each deadline and spins only
  that long: a SCHED_FIFO thread that is busy past /proc/sys/kernel/sched_rt_runtime_us (950 ms of
  every 1 s) is throttled by the kernel for the rest of that second (docs/realtime.md).
  On a loaded machine run the cycle at --rt-priority N (SCHED_FIFO, needs CAP_SYS_NICE); the process's
  other threads (Cyclone DDS's) then run at N-1, so the cycle preempts them when its deadline comes. A
  cycle thread starved for longer than the drives' SyncManager watchdog (100 ms by default) drops them
  to SAFE-OP, and the bus latches its safe stop; beside two CPU burners this happened in 9 of 14
  served starts at normal priority and in 0 of 8 at --rt-priority 50 (docs/dds.md).
"""
EXIT_CODES = [
    (0, "stopped by SIGTERM (a served bus's normal end) or after --cycles; the drives were stopped"),
    (1, "bring-up, file or argument error (the message names file, drive, object)"),
    (143, "not used: SIGTERM is serve's normal end (exit 0)"),
]


def register(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "serve",
        help="run a network's cycle and serve it over DDS (ROS 2 compatible)",
        description="Run a network's cycle and serve it over Cyclone DDS, with ROS 2 type and topic names.",
        epilog=HELP_EPILOG + "\n" + epilog(EXIT_CODES, live_bus=True, json=False),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("network", metavar="NETWORK.yaml", help="network file to serve")
    p.add_argument("--backend", help="run every bus on this backend instead (e.g. sim)")
    p.add_argument("--namespace", help="topic namespace (default: the network's name)")
    p.add_argument("--domain", type=int, metavar="N", help="DDS domain id (see below)")
    p.add_argument("--interface", metavar="IF", help="network interface for DDS (see below)")
    p.add_argument("--peer", action="append", default=[], metavar="ADDR", help="unicast discovery peer")
    p.add_argument("--cycles", type=int, default=0, help="stop after N cycles (default 0: until SIGTERM)")
    p.add_argument("--publish-every", type=int, default=1, metavar="N", help="publish state every N-th cycle")
    p.add_argument(
        "--diagnostics-every", type=int, default=1000, metavar="N", help="diagnostics every N cycles"
    )
    p.add_argument("--hold-after", type=int, default=20, metavar="N", help="cycles without a command: hold")
    p.add_argument(
        "--stop-after", type=int, default=200, metavar="M", help="cycles without a command: safe stop"
    )
    p.add_argument(
        "--base-namespace",
        default="",
        metavar="NS",
        help="the wheeled base's topics (cmd_vel, odom, joint_states, diagnostics) under /NS "
        "(default: the global names Nav2 uses; tf is always /tf)",
    )
    p.add_argument(
        "--ros2-control",
        nargs="?",
        const="/robot_joint_commands,/robot_joint_states",
        metavar="COMMANDS,STATES",
        help="serve ros2_control's topic-based hardware interface: commands (sensor_msgs/JointState) on "
        "COMMANDS, every joint's state on STATES (default: /robot_joint_commands,/robot_joint_states)",
    )
    p.add_argument("--json", action="store_true", help="ready line and final report as JSON objects")
    p.add_argument(
        "--spin-us",
        type=int,
        default=30,
        metavar="US",
        help="after an absolute sleep, spin this long before each cycle's deadline (default 30)",
    )
    cycleopts.add_arguments(p, plot=False)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from fieldbus import dds

    dds.require()
    from fieldbus.core.network import load_network
    from fieldbus.dds.participant import Participant
    from fieldbus.dds.server import BusServer
    from fieldbus.errors import FieldbusError
    from fieldbus.network import open_network
    from fieldbus.operations.report import run_report
    from fieldbus.platform.clock import DeadlineClock
    from fieldbus.platform.rt import thread_ids

    if args.cycles < 0:
        raise FieldbusError("--cycles must be >= 0 (0: until SIGTERM)")
    if not 0 <= args.spin_us <= 1000:
        raise FieldbusError(f"--spin-us must be 0..1000 µs, not {args.spin_us}")
    model = load_network(args.network)
    options = _options(args, model.name)
    cycleopts.check_record(args)
    stopping = False

    def on_term(_sig: int, _frame: FrameType | None) -> None:
        nonlocal stopping
        stopping = True

    previous = signal.signal(signal.SIGTERM, on_term)
    try:
        # memory locked and the CPU pinned first; participant, network and topics at normal priority
        with cycleopts.rt_context(args, fifo_later=True) as rt:
            before = set(thread_ids())
            participant = Participant(args.domain, args.interface, args.peer)
            with open_network(model, backend=args.backend) as net:
                server = BusServer(net, participant, options)
                cycleopts.cycle_priority(rt, before, others_below=1)
                op = net.bring_up()
                server.attach(op)
                cycleopts.start_recording(op, args)
                _others_below(rt)
                print(
                    json.dumps(_ready(server, options.namespace, participant.domain_id, rt.to_json()))
                    if args.json
                    else f"serving '{options.namespace}' on DDS domain "
                    f"{participant.domain_id}: {', '.join(server.groups)} (ready)",
                    flush=True,
                )

                def step(k: int) -> bool:
                    server.step(k)
                    return stopping

                period = float(op.cycle_time_us)
                # an absolute sleep to 30 us before each deadline: a spin of 150 us a cycle on top of the
                # step kept the SCHED_FIFO thread busy enough for the kernel's RT throttling (docs/dds.md)
                timer, _ = cycleopts.run_timed(
                    op,
                    step,
                    period,
                    args.cycles or sys.maxsize,
                    status=False,
                    clock=DeadlineClock(args.spin_us * 1000),
                )
                report = run_report(op, timer, period)
    finally:
        signal.signal(signal.SIGTERM, previous)
    report.update(_served(server))
    if server.stalls.note:
        print(f"fieldbus serve: {server.stalls.note}", file=sys.stderr)
    if args.json:
        print(json.dumps(report))
    else:
        print(
            f"served {report['cycles']} cycles: missed {report['missed']}, safe stops {report['safe_stops']}"
        )
    return 0


def _others_below(rt: RtState) -> None:
    """Threads made since the cycle took its priority (a recorder's) one below it, and with ``--cpu`` every
    other thread off the cycle's one CPU again."""
    from fieldbus.platform.rt import rank_below, unpin_others

    if rt.fifo is not None and not (line := rank_below(rt.fifo)).startswith("0 "):
        rt.applied.append(line)
    if rt.cpus_before is not None:
        rt.applied.append(unpin_others(rt.cpus_before))


def _options(args: argparse.Namespace, network_name: str) -> ServeOptions:
    """The server's options from the command line (namespace default: the network's name)."""
    from fieldbus.dds.gate import Deadline
    from fieldbus.dds.participant import check_namespace
    from fieldbus.dds.server import ServeOptions

    return ServeOptions(
        namespace=check_namespace(args.namespace or network_name),
        deadline=Deadline(args.hold_after, args.stop_after),
        publish_every=args.publish_every,
        diagnostics_every=args.diagnostics_every,
        base_namespace=check_namespace(args.base_namespace) if args.base_namespace else "",
        ros2_control=_topic_pair(args.ros2_control) if args.ros2_control else None,
    )


def _ready(server: BusServer, namespace: str, domain: int, realtime: dict[str, Any]) -> dict[str, Any]:
    """The ``--json`` ready line: where every group, the base and the ros2_control topics are served."""
    return {
        "ready": True,
        "namespace": namespace,
        "domain": domain,
        "groups": {n: g.topics for n, g in server.groups.items()},
        **({"base": server.base.topics} if server.base is not None else {}),
        **({"ros2_control": server.topic_control.topics} if server.topic_control is not None else {}),
        "realtime": realtime,
    }


def _served(server: BusServer) -> dict[str, Any]:
    """What the report adds for a served bus: each group's gate, the requests, the cycle's stalls."""
    w = server.stalls
    return {
        "groups": {
            n: {
                "owner": g.gate.label if g.gate.owner is not None else None,
                "gate": g.gate.state.name,
                "dropped": g.gate.dropped,
                "refused": g.gate.refused,
            }
            for n, g in server.groups.items()
        },
        "requests": server.requests,
        "stalls": {
            "count": w.count,
            "longest_us": w.longest_ns // 1000,
            "longest_gap_us": w.longest_gap_ns // 1000,  # between two cycles' starts: period + lateness
            "over_5ms": w.over_5ms,  # gaps between two cycles' starts longer than 5 ms
            # the newest 64 of them: [cycle started late, gap us, its start: CLOCK_MONOTONIC ns]
            "over_5ms_at": [[c, g // 1000, t] for c, g, t in w.over_5ms_at],
            "note": w.note,
        },
    }


def _topic_pair(text: str) -> tuple[str, str]:
    """``COMMANDS,STATES``: two ROS 2 topic names."""
    from fieldbus.dds.participant import check_namespace
    from fieldbus.errors import FieldbusError

    parts = [p.strip() for p in text.split(",")]
    if len(parts) != 2 or not all(parts):
        raise FieldbusError(f"--ros2-control takes COMMANDS,STATES (two topic names), not {text!r}")
    return check_namespace(parts[0]), check_namespace(parts[1])
