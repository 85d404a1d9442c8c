"""CAN emulators in their own process, so a test or benchmark measures the master, not two threads.

In one process the emulated nodes and the master share one interpreter lock: the
nodes' work lands inside the master's cycle. Here a child process runs
:class:`~sim_slaves.canopen.CanopenSimulator` (``--kind canopen``) or the raw-CAN
motors of a map's family (:mod:`sim_slaves.can_families`): ``--kind auto`` takes the
family from the map; ``mit``, ``damiao``, ``odrive``, ``cubemars`` (servo or MIT by
the map) say which it must be, and a map of another family is refused. On a python-can
bus that crosses processes: ``fieldbus_udp`` (:mod:`fieldbus.backends.udpcan`,
fixed-size datagrams on the loopback, the lean one), python-can's
``udp_multicast`` (msgpack per frame, needs msgpack), one group and port per
bus, or any other python-can interface.

    python -m sim_slaves.can_process --kind mit --map MAP.yaml --nodes 1,2,3 \\
        --interface fieldbus_udp --channel 239.74.163.2 --option port=43114 \\
        [--channel 239.74.163.3 --option port=43115 ...]

Several ``--channel``: one bus each, all served by one thread
(:func:`sim_slaves.busthread.serve_together`: one ``select`` over the buses), so
the emulators of a robot's buses take one CPU between them instead of one process
each. An ``--option``, ``--kind``, ``--map`` or ``--nodes`` belongs to the
``--channel`` before it (to every bus when it comes first): buses of different
families and maps in one process. Prints ``ready`` once the nodes listen and runs
until SIGTERM or SIGINT, also in the background with its stdin closed; with
``--exit-with-stdin`` (what :func:`can_emulator_process` passes, so a parent
killed without cleaning up takes its child along) it also stops when its stdin
closes, and says so on stderr. :func:`can_emulator_process` starts
one from Python and stops it; :func:`udp_bus` picks a group and port nobody
else on this host uses, for either UDP interface.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import select
import signal
import socket
import subprocess
import sys
import tempfile
import threading
from collections.abc import Iterator, Sequence
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from fieldbus.core.canfamily import families
from fieldbus.core.rawcan import FAMILIES
from sim_slaves.busthread import serve_together

READY_TIMEOUT_S = 20.0
UDP_GROUP_BASE = "239.74.163."  # administratively scoped IPv4 multicast (python-can's default group is .2)
UDP_INTERFACES = ("udp_multicast", "fieldbus_udp")  # python-can interfaces udp_bus() can describe
# the raw-CAN families: the classic ones and those of the one table (fieldbus.core.canfamily)
KINDS = ("canopen", *dict.fromkeys((*FAMILIES, *families())), "auto")


@dataclass(frozen=True)
class CanChannel:
    """Where a bus is: python-can interface type, channel and extra Bus arguments."""

    interface: str
    channel: str
    options: tuple[tuple[str, str | int | float | bool], ...] = ()

    def network_keys(self) -> str:
        """The bus keys of a network file (flow style) for this channel."""
        opts = ", ".join(f"{k}: {v}" for k, v in self.options)
        return f"interface: '{self.channel}', can_interface: {self.interface}" + (
            f", can_options: {{{opts}}}" if opts else ""
        )


def udp_bus(index: int = 0, interface: str = "udp_multicast") -> CanChannel:
    """A UDP multicast channel for bus ``index``: its own group and a UDP port free on this host.

    ``interface``: ``udp_multicast`` (python-can's, msgpack per frame; the default,
    so existing callers keep measuring what they did) or ``fieldbus_udp``
    (:mod:`fieldbus.backends.udpcan`: fixed-size datagrams, no msgpack; a send
    plus a receive 14 µs against 48 µs on a 2-CPU VM). Groups sharing a port would hear each other on
    ``udp_multicast`` (Linux delivers a group's datagrams to every socket bound
    to the port), so each bus gets its own port.
    """
    if interface not in UDP_INTERFACES:
        raise ValueError(f"udp_bus: interface must be one of {', '.join(UDP_INTERFACES)}, got '{interface}'")
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    return CanChannel(interface, f"{UDP_GROUP_BASE}{2 + index % 250}", (("port", port),))


def _option(text: str) -> tuple[str, str | int | float | bool]:
    key, sep, value = text.partition("=")
    if not sep or not key:
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE, got '{text}'")
    parsed: str | int | float | bool = value
    if value in ("true", "false"):
        parsed = value == "true"
    else:
        for kind in (int, float):
            try:
                parsed = kind(value)
                break
            except ValueError:
                continue
    return key, parsed


def _stop_when_stdin_closes(stop: threading.Event) -> None:
    """``--exit-with-stdin``: the parent went away when stdin closes (it never writes to it)."""
    sys.stdin.readline()
    print("can_process: stdin closed (--exit-with-stdin): stopping", file=sys.stderr, flush=True)
    stop.set()


class _ChannelAction(argparse.Action):
    """``--channel``: a new bus (its channel and, from the ``--option``\\s after it, its options)."""

    def __call__(self, parser: Any, namespace: Any, values: Any, option_string: Any = None) -> None:
        namespace.buses = [*(namespace.buses or []), (str(values), {})]
        namespace.per_bus = [*(getattr(namespace, "per_bus", None) or []), {}]


class _BusSpecAction(argparse.Action):
    """``--kind``, ``--map``, ``--nodes``: for the last ``--channel``, or for every bus before the first."""

    def __call__(self, parser: Any, namespace: Any, values: Any, option_string: Any = None) -> None:
        if namespace.buses:
            namespace.per_bus[-1][self.dest] = values
        else:
            setattr(namespace, self.dest, values)


class _OptionAction(argparse.Action):
    """``--option KEY=VALUE``: for the last ``--channel``, or for every bus before the first."""

    def __call__(self, parser: Any, namespace: Any, values: Any, option_string: Any = None) -> None:
        key, value = values
        if namespace.buses:
            namespace.buses[-1][1][key] = value
        else:
            namespace.common = {**(namespace.common or {}), key: value}


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    """The command line (see the module)."""
    p = argparse.ArgumentParser(prog="python -m sim_slaves.can_process", description=__doc__.splitlines()[0])
    p.add_argument(
        "--kind",
        choices=KINDS,
        action=_BusSpecAction,
        help="the nodes' emulator; auto: the raw-CAN family of the map (after a --channel: that bus's)",
    )
    p.add_argument(
        "--map", action=_BusSpecAction, help="drive map of every node (after a --channel: that bus's)"
    )
    p.add_argument(
        "--nodes", action=_BusSpecAction, help="node ids, e.g. 1,2,3 (after a --channel: that bus's)"
    )
    p.add_argument(
        "--interface",
        default="udp_multicast",
        help="python-can interface (default udp_multicast; fieldbus_udp is the lean one)",
    )
    p.add_argument(
        "--channel", dest="buses", action=_ChannelAction, required=True, help="a bus (repeat for several)"
    )
    p.add_argument(
        "--option",
        dest="common",
        type=_option,
        action=_OptionAction,
        help="more Bus arguments, KEY=VALUE, for the --channel before it (every bus when first)",
    )
    p.add_argument("--dt-s", type=float, help="the drives' time step per SYNC / command (s)")
    p.add_argument(
        "--exit-with-stdin",
        action="store_true",
        help="also stop when stdin closes (a parent holding a pipe to it went away); "
        "default: only SIGTERM/SIGINT stop it",
    )
    args = p.parse_args(argv)
    per_bus = getattr(args, "per_bus", None) or [{} for _ in args.buses]
    for (channel, _), own in zip(args.buses, per_bus, strict=True):
        missing = [k for k in ("kind", "map", "nodes") if own.get(k, getattr(args, k)) is None]
        if missing:
            p.error(
                f"bus {channel}: no {', '.join('--' + k for k in missing)} (give it before the first --channel)"
            )
    args.per_bus = per_bus
    return args


def bus_specs(args: argparse.Namespace) -> list[tuple[str, str, list[int]]]:
    """Each bus's ``(kind, map, node ids)`` of parsed ``args``, in ``--channel`` order."""
    out = []
    for own in args.per_bus:
        kind, drive_map, nodes = (own.get(k, getattr(args, k)) for k in ("kind", "map", "nodes"))
        out.append((str(kind), str(drive_map), [int(n) for n in str(nodes).split(",")]))
    return out


def _emulator(kind: str, bus: Any, drive: Any, node_ids: list[int], dt_s: float | None) -> Any:
    """The emulator of ``kind`` for ``node_ids`` of ``drive`` on ``bus``; ``ValueError`` for a map of another
    family than ``kind`` says."""
    motors = [(drive, n) for n in node_ids]
    if kind == "canopen":
        from sim_slaves.canopen import CanopenSimulator

        return CanopenSimulator(bus, motors, dt_s=dt_s)
    from sim_slaves.can_families import family_of, simulator

    family = family_of(drive)
    if kind != "auto" and family.split("-")[0] != kind:
        raise ValueError(f"--kind {kind}: the map {drive.name} is of family {family}")
    return simulator(bus, motors, dt_s=dt_s)


def bus_arguments(args: argparse.Namespace) -> list[dict[str, Any]]:
    """``can.Bus`` keyword arguments of every bus of parsed ``args``, in ``--channel`` order."""
    return [
        {"interface": args.interface, "channel": channel, **(args.common or {}), **options}
        for channel, options in args.buses
    ]


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)

    import can

    from fieldbus.core.pdo import load_drive_map

    specs = bus_specs(args)
    drives = {path: load_drive_map(path) for _, path, _ in specs}
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    if args.exit_with_stdin:
        threading.Thread(target=_stop_when_stdin_closes, args=(stop,), daemon=True).start()
    with ExitStack() as stack:
        try:
            sims = [
                _emulator(kind, stack.enter_context(can.Bus(**kwargs)), drives[path], nodes, args.dt_s)
                for kwargs, (kind, path, nodes) in zip(bus_arguments(args), specs, strict=True)
            ]
        except ValueError as exc:
            print(f"can_process: {exc}", file=sys.stderr, flush=True)
            return 2
        if len(sims) == 1:
            with sims[0]:
                print("ready", flush=True)
                while not stop.wait(0.2):
                    pass
        else:
            serving = threading.Thread(target=serve_together, args=(sims, stop), name="can-emulators")
            serving.start()  # boots the nodes first; "ready" follows at once, as with one bus
            print("ready", flush=True)
            serving.join()
        for sim in sims:
            if sim.errors:
                print("\n".join(sim.errors), file=sys.stderr)
    return 0


@dataclass(frozen=True)
class EmulatedBus:
    """One bus of an emulator process: the emulator kind (``--kind``), drive map, node ids and channel."""

    kind: str
    drive_map: str | Path
    node_ids: Sequence[int]
    where: CanChannel


def can_emulator_process(
    kind: str,
    drive_map: str | Path,
    node_ids: Sequence[int],
    where: CanChannel | Sequence[CanChannel],
    *,
    dt_s: float | None = None,
) -> contextlib.AbstractContextManager[subprocess.Popen[str]]:
    """Run emulated nodes in a child process on ``where``; stopped (SIGTERM) on exit.

    Several channels: the same nodes on each, every bus served by the child's one thread.
    """
    channels = [where] if isinstance(where, CanChannel) else list(where)
    return can_emulators_process([EmulatedBus(kind, drive_map, node_ids, c) for c in channels], dt_s=dt_s)


@contextmanager
def can_emulators_process(
    buses: Sequence[EmulatedBus], *, dt_s: float | None = None
) -> Iterator[subprocess.Popen[str]]:
    """Run the emulators of several buses (each its kind, map and nodes) in one child process, every bus
    served by its one thread; stopped (SIGTERM) on exit. ``RuntimeError`` when it does not start."""
    interfaces = {b.where.interface for b in buses}
    if len(interfaces) != 1:
        raise ValueError(f"can_emulator_process: one interface for every bus, got {sorted(interfaces)}")
    cmd = [
        sys.executable,
        "-m",
        "sim_slaves.can_process",
        "--interface",
        buses[0].where.interface,
        "--exit-with-stdin",
    ]
    for b in buses:
        cmd += ["--channel", b.where.channel]
        cmd += ["--kind", b.kind, "--map", str(b.drive_map), "--nodes", ",".join(str(n) for n in b.node_ids)]
        for key, value in b.where.options:
            cmd += ["--option", f"{key}={str(value).lower() if isinstance(value, bool) else value}"]
    if dt_s is not None:
        cmd += ["--dt-s", str(dt_s)]
    env = dict(os.environ)
    root = str(Path(__file__).resolve().parents[1])
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    errors = tempfile.TemporaryFile(mode="w+")  # noqa: SIM115 - closed below; never a pipe nobody drains
    proc = subprocess.Popen(
        cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=errors, text=True, env=env
    )
    try:
        assert proc.stdout is not None
        ready, _, _ = select.select([proc.stdout], [], [], READY_TIMEOUT_S)
        line = proc.stdout.readline() if ready else ""
        if line.strip() != "ready":
            proc.kill()
            proc.wait(timeout=5)
            errors.seek(0)
            tail = errors.read()[-2000:]
            raise RuntimeError(f"CAN emulator process did not start ({line.strip()!r}): {tail.strip()}")
        yield proc
    finally:
        errors.close()
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


if __name__ == "__main__":
    sys.exit(main())
