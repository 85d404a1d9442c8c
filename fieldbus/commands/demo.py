"""``fieldbus demo``: the main job on the built-in emulators.

Brings up N emulated CiA 402 joints (``fieldbus/data/demo_joint.yaml``),
enables them all through the CiA 402 state machine, makes them follow a
smooth sine in cyclic synchronous position mode and prints tracking error and
cycle statistics.

Backends: ``sim`` (the EtherCAT emulator in-process: real frames, no root),
``ethercat`` (pysoem over a veth pair the demo creates, the emulator in a
child process; needs root), ``canopen`` (emulated nodes on python-can's
virtual bus), ``rawcan`` (raw-CAN motors of a shipped map on python-can's virtual bus: ``--motor``
picks the map, a shipped one by name or any raw-CAN map by its path, so each family - MIT, Damiao, ODrive, CubeMars servo or MIT - runs on its own emulator,
found through the ``can_motor_simulator`` emulator part).
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from fieldbus.commands import buslogs, cycleopts
from fieldbus.commands.argtypes import UsageError, integer, non_negative, number
from fieldbus.commands.outputs import check_plot
from fieldbus.commands.usage import add_command
from fieldbus.core.canfamily import families
from fieldbus.core.cia402 import Cia402Controller, Goal, Mode, State402
from fieldbus.core.network import load_network
from fieldbus.emulators import emulator_part
from fieldbus.errors import FieldbusError, PdoMapError
from fieldbus.network import Network, Operational, open_network
from fieldbus.operations.report import run_report
from fieldbus.platform.rt import RtState, thread_ids

DEMO_MAP = Path(__file__).resolve().parents[1] / "data" / "demo_joint.yaml"
BACKENDS = ("sim", "ethercat", "canopen", "rawcan")
PDO_MAPS = Path(__file__).resolve().parents[1] / "pdo_maps"  # package data
MIT_MAP = PDO_MAPS / "cubemars_ak80_9_mit.yaml"
# --motor: the shipped raw-CAN maps (tests check the list against pdo_maps/), the default first
MOTORS = (
    "cubemars_ak80_9_mit",
    "cubemars_ak10_9_mit",
    "cubemars_ak80_9_servo",
    "damiao_dm_j4310",
    "damiao_dm_j4340",
    "damiao_dm_j8009",
    "odrive_s1",
    "odrive_3_6",
    "amr_seed_wheels",
)
SERVO_SPEED_LIMIT = 10.0  # rad/s, the CubeMars servo demo's position-speed limit
AMPLITUDE_RAD = 0.5  # sine amplitude per joint
FREQUENCY_HZ = 0.5
ENABLE_TIMEOUT_S = 3.0
# A frame that returns later than this counts as a miss. The veth emulator is a
# user-space process on a shared machine: give it more than the 500 us default.
# python-can's virtual bus is threads in one process: not real time (GIL switch interval 5 ms).
RECEIVE_TIMEOUT_US = {"sim": 500, "ethercat": 2000, "canopen": 20000, "rawcan": 20000}


EXIT_CODES = [
    (
        0,
        "every axis reached OPERATION ENABLED and no safe stop was triggered\n"
        "(misses the policy absorbed - late or lost frames, inputs held - are counted\n"
        'in the output, "missed", and do not fail the demo)',
    ),
    (
        1,
        "bring-up error, or an output file that cannot be written (the message names the drive,\nobject or file)",
    ),
    (3, "an axis never reached OPERATION ENABLED, or a safe stop was triggered"),
]
GENERATED = "the demo's generated network"
MAX_CAN_AXES = 127  # CANopen node ids and the MIT motors' ids: 1..127, one per axis
RATE_HZ = (1.0, 20_000.0)  # the network file's cycle_time_us range, 50 us .. 1 s


def register(sub: Any) -> None:
    p = add_command(
        sub,
        "demo",
        help="enable emulated CiA 402 joints and follow a sine (the main job)",
        doc="Bring up emulated drives, enable every axis through CiA 402, follow a 0.5 rad / 0.5 Hz "
        "sine and print tracking error and cycle statistics.",
        codes=EXIT_CODES,
        live_bus=True,
    )
    p.add_argument("--backend", choices=BACKENDS, default="sim", help="bus to run on (default sim)")
    p.add_argument(
        "--axes",
        type=integer(1),
        default=None,
        help=f"number of joints (default 12, or as many as the motor's shared frames carry; canopen, "
        f"rawcan: at most {MAX_CAN_AXES})",
    )
    p.add_argument("--cycles", type=integer(1), default=3000, help="cycles to run (default 3000)")
    p.add_argument(
        "--rate",
        type=number(*RATE_HZ, unit="Hz"),
        default=None,
        help="cycle rate in Hz, 1 to 20000 (default 1000; canopen 100, rawcan 250: python-can's virtual "
        "bus is threads)",
    )
    p.add_argument(
        "--motor",
        default=None,
        metavar="MAP",
        help=f"rawcan: the motors' drive map, a shipped one ({', '.join(MOTORS)}) or a raw-CAN map's "
        f"path, each family on its own emulator (default {MOTORS[0]})",
    )
    p.add_argument("--json", action="store_true", help="one JSON object on stdout")
    p.add_argument(
        "--delay-us",
        type=non_negative("us"),
        default=0.0,
        help="sim, ethercat: every emulated drive acts on its targets this late "
        "(emulator command_delay_us; default 0)",
    )
    p.add_argument(
        "--latency",
        action="store_true",
        help="measure each axis's command-to-feedback delay instead (see latency)",
    )
    cycleopts.add_arguments(p)
    buslogs.add_arguments(p)
    cycleopts.add_monitor_argument(p)
    p.set_defaults(func=run)


DEFAULT_RATE_HZ = {"sim": 1000.0, "ethercat": 1000.0, "canopen": 100.0, "rawcan": 250.0}


def run(args: argparse.Namespace) -> int:
    if args.rate is None:
        args.rate = DEFAULT_RATE_HZ[args.backend]
    if args.motor is not None and args.backend != "rawcan":
        raise UsageError("--motor needs --backend rawcan (the raw-CAN motors' drive map)")
    args.motor = args.motor or MOTORS[0]
    if args.axes is None:
        top = max_motor_axes(args.motor) if args.backend == "rawcan" else None
        args.axes = min(12, top) if top is not None else 12
    check_axes(args.backend, args.axes)
    if args.backend == "rawcan":
        check_motor_axes(args.motor, args.axes)
    if args.delay_us and args.backend not in ("sim", "ethercat"):
        raise UsageError("--delay-us needs --backend sim or ethercat (the EtherCAT emulators)")
    if args.latency:
        return _latency(args)
    check_plot(args.plot, "--plot")
    buslogs.check_outputs(args)
    cycleopts.check_record(args)
    # memory locked and the CPU pinned first; the set-up (emulators, network) at normal priority
    with cycleopts.rt_context(args, fifo_later=True) as rt:
        report = run_demo(
            args.backend,
            args.axes,
            args.cycles,
            args.rate,
            status=not args.json,
            rt=rt,
            logs=args,
            delay_us=args.delay_us,
            motor=args.motor,
        )
    if args.plot:
        cycleopts.plot_latency(report.pop("_latency"), args.plot, f"fieldbus demo --backend {args.backend}")
    report.pop("_latency", None)
    if args.json:
        print(json.dumps(report))
    else:
        print(describe(report))
    return 0 if report["enabled"] and report["safe_stops"] == 0 else 3


def check_axes(backend: str, axes: int) -> None:
    """CAN backends number their axes by node id: :class:`UsageError` past :data:`MAX_CAN_AXES`."""
    if backend in ("canopen", "rawcan") and axes > MAX_CAN_AXES:
        raise UsageError(
            f"--backend {backend} takes at most {MAX_CAN_AXES} axes (node ids 1..127), not {axes}"
        )


def motor_map(motor: str) -> Path:
    """The drive map of ``--motor``: a shipped map's name (:data:`MOTORS`) or a map file's path."""
    if motor in MOTORS:
        return PDO_MAPS / f"{motor}.yaml"
    path = Path(motor)
    if path.suffix in (".yaml", ".yml") and path.is_file():
        return path.resolve()  # the generated network sits elsewhere
    raise UsageError(f"--motor {motor}: neither a shipped map ({', '.join(MOTORS)}) nor a map file")


def _rawcan_config(motor: str) -> Any:
    from fieldbus.core.pdo import load_drive_map

    cfg = load_drive_map(motor_map(motor)).rawcan
    if cfg is None:
        raise UsageError(f"--motor {motor}: the map has no rawcan section (raw-CAN motors only)")
    return cfg


def motor_family(motor: str) -> str:
    """The raw-CAN family of ``motor`` (``mit``, ``damiao``, ``odrive``, ``cubemars``, ``frames``)."""
    return str(_rawcan_config(motor).family)


def max_motor_axes(motor: str) -> int | None:
    """Most axes ``motor``'s ids allow (its family's :meth:`CanFamily.max_motors`: Damiao's MST_ID
    offset, ODrive's node ids, the slots of a shared frame), or None for no limit."""
    cfg = _rawcan_config(motor)
    family = families().get(cfg.family)
    return None if family is None else family.max_motors(cfg.protocol)


def check_motor_axes(motor: str, axes: int) -> None:
    """:class:`UsageError` for more axes than the family's ids allow (:func:`max_motor_axes`)."""
    top = max_motor_axes(motor)
    if top is not None and axes > top:
        raise UsageError(f"--motor {motor} takes at most {top} axes (its CAN ids), not {axes}")


def _latency(args: argparse.Namespace) -> int:
    """``demo --latency``: the latency measurement on the demo's joints."""
    from fieldbus.commands import latency

    with (
        tempfile.TemporaryDirectory(prefix="fieldbus-demo-") as tmp,
        demo_network(
            args.backend, args.axes, args.rate, Path(tmp), delay_us=args.delay_us, motor=args.motor
        ) as setup,
    ):
        report = latency.measure_latency(str(setup.net_file), setup.backend)
    print(json.dumps(report) if args.json else latency.describe(report))
    return 0 if report["enabled"] else 3


def describe(r: dict[str, Any]) -> str:
    t, e = r["cycle_time_us"], r["tracking_error"]
    lines = [
        f"{r['axes']} {_what(r)} on '{r['backend']}', {r['cycles']} cycles at {1e6 / r['period_us']:g} Hz",
        f"  enabled: {'all' if r['enabled'] else 'NOT all'} after {r['enable_cycles']} cycles",
        f"  tracking error (sine {AMPLITUDE_RAD} rad, {FREQUENCY_HZ} Hz): max {e['max_rad'] * 1e3:.3f} mrad, "
        f"rms {e['rms_rad'] * 1e3:.3f} mrad",
        f"  cycle work: mean {t['mean']} us, p99 {t['p99']} us, max {t['max']} us; overruns {r['overruns']}",
        f"  missed {r['missed']}, safe stops {r['safe_stops']}",
    ]
    if r.get("motor_faults"):
        lines.append(f"  motor faults: {'; '.join(r['motor_faults'])}")
    if not r["enabled"]:
        lines.append(f"  states: {', '.join(r['states'])}")
    return "\n".join(lines)


def _what(r: dict[str, Any]) -> str:
    if r["backend"] != "rawcan":
        return "CiA 402 joints"
    motor = r.get("motor", MOTORS[0])
    return "MIT-mode motors" if motor == MOTORS[0] else f"{motor} motors"


@dataclass
class DemoSetup:
    """The demo's network file, the backend to open it with, and its emulator (for fault hooks)."""

    net_file: Path
    backend: str | None
    emulator: Any = (
        None  # sim: None (the chain lives in the backend); ethercat: veth Emulator; canopen: simulator
    )

    def control(self, net: Network, **msg: Any) -> dict[str, Any]:
        """An EtherCAT emulator command (``sim_slaves.ethercat.runner.handle_control``): drop, status, ..."""
        if self.backend == "sim":
            status: dict[str, Any] = emulator_part("ethercat_control")(net.backends[0].chain, msg)  # type: ignore[attr-defined]
            return status
        if self.backend is None and type(self.emulator).__name__ == "CanopenSimulator":
            answer: dict[str, Any] = emulator_part("canopen_control")(self.emulator, msg)
            return answer
        if hasattr(self.emulator, "command"):
            result: dict[str, Any] = self.emulator.command(**msg)
            return result
        raise FieldbusError("this demo backend has no EtherCAT emulator control")


@contextmanager
def demo_network(
    backend: str, axes: int, rate_hz: float, workdir: Path, *, delay_us: float = 0.0, motor: str = MOTORS[0]
) -> Iterator[DemoSetup]:
    """Write the demo's network file and start its emulator (``delay_us``: the emulated drives' command delay;
    ``motor``: rawcan, the shipped map of the motors, :data:`MOTORS`).

    An error about the files written into ``workdir`` (a temporary folder the user never saw)
    names :data:`GENERATED` instead, with the field path."""
    try:
        yield from _setups(backend, axes, rate_hz, workdir, delay_us, motor)
    except FieldbusError as exc:
        raise _generated(exc, workdir) from None


def _generated(exc: FieldbusError, workdir: Path) -> FieldbusError:
    """``exc`` with the demo's generated files in ``workdir`` named as :data:`GENERATED`."""
    files = [str(workdir / name) for name in ("demo.yaml", "emulated.yaml")]
    if isinstance(exc, PdoMapError) and exc.file in files:
        where = f"{GENERATED}, {exc.path}" if exc.path else GENERATED
        return FieldbusError(f"{where}: {exc.message}")
    text = str(exc)
    if not any(f in text for f in files):
        return exc
    for f in files:
        text = text.replace(f, GENERATED)
    return FieldbusError(text)


def _setups(
    backend: str, axes: int, rate_hz: float, workdir: Path, delay_us: float, motor: str = MOTORS[0]
) -> Iterator[DemoSetup]:
    cycle_us = max(1, round(1e6 / rate_hz))
    head = f"name: demo\ncycle_time_us: {cycle_us}\nreceive_timeout_us: {RECEIVE_TIMEOUT_US[backend]}\n"
    options = f", emulator: {{command_delay_us: {delay_us:.3f}}}" if delay_us else ""  # a dot: a YAML float
    slaves = f"    slaves: [{{name: 'j{{i}}', map: {json.dumps(str(DEMO_MAP))}, count: {axes}{options}}}]\n"
    net = workdir / "demo.yaml"
    if backend == "sim":
        net.write_text(head + "buses:\n  - name: joints\n    type: ethercat\n    interface: sim\n" + slaves)
        yield DemoSetup(net, "sim")
    elif backend == "ethercat":
        emulated_segment = emulator_part("veth_segment")
        # the emulator builds its drives (and their emulator: options) from the same slaves
        emulated = workdir / "emulated.yaml"
        emulated.write_text(
            head + "buses:\n  - name: joints\n    type: ethercat\n    interface: veth\n" + slaves
        )
        with emulated_segment([DEMO_MAP], workdir=workdir, network=emulated) as emu:
            net.write_text(
                head + f"buses:\n  - name: joints\n    type: ethercat\n    interface: {emu.iface}\n" + slaves
            )
            yield DemoSetup(net, None, emu)
    elif backend == "canopen":
        yield from _canopen_network(head, axes, net)
    elif backend == "rawcan":
        yield from _rawcan_network(head, axes, rate_hz, net, motor)
    else:
        raise FieldbusError(f"unknown demo backend '{backend}' (have: {', '.join(BACKENDS)})")


def _canopen_network(head: str, axes: int, net: Path) -> Iterator[DemoSetup]:
    try:
        import can

        from fieldbus.core.pdo import load_drive_map

        CanopenSimulator = emulator_part("canopen_simulator")
    except ImportError as exc:
        raise FieldbusError(f"the canopen demo needs {exc.name}: pip install 'fieldbus[can]'") from None
    channel = f"fieldbus-demo-{id(net)}"
    drive = load_drive_map(DEMO_MAP)
    net.write_text(
        head + "buses:\n  - name: joints\n    type: canopen\n"
        f"    interface: {channel}\n    can_interface: virtual\n"
        f"    slaves: [{{name: 'j{{i}}', map: {json.dumps(str(DEMO_MAP))}, node_id: 1, count: {axes}}}]\n"
    )
    with (
        can.Bus(interface="virtual", channel=channel) as bus,
        CanopenSimulator(bus, [(drive, n) for n in range(1, axes + 1)]) as sim,
    ):
        yield DemoSetup(net, None, sim)


def _rawcan_network(
    head: str, axes: int, rate_hz: float, net: Path, motor: str = MOTORS[0]
) -> Iterator[DemoSetup]:
    """Raw-CAN motors of the shipped map ``motor`` emulated on python-can's virtual bus, each family by its
    own emulator (the ``can_motor_simulator`` emulator part: the family from the map)."""
    try:
        import can

        from fieldbus.core.pdo import load_drive_map

        simulator = emulator_part("can_motor_simulator")
    except ImportError as exc:
        raise FieldbusError(f"the rawcan demo needs {exc.name}: pip install 'fieldbus[can]'") from None
    try:
        drive_map = motor_map(motor)
    except UsageError as exc:
        raise FieldbusError(str(exc)) from None
    channel = f"fieldbus-demo-{drive_map.stem}-{id(net)}"
    drive = load_drive_map(drive_map)
    net.write_text(
        head + "buses:\n  - name: joints\n    type: rawcan\n"
        f"    interface: {channel}\n    can_interface: virtual\n"
        f"    slaves: [{{name: 'm{{i}}', map: {json.dumps(str(drive_map))}, node_id: 1, count: {axes}}}]\n"
    )
    with (
        can.Bus(interface="virtual", channel=channel) as bus,
        simulator(bus, [(drive, n) for n in range(1, axes + 1)], dt_s=1.0 / rate_hz) as sim,
    ):
        yield DemoSetup(net, None, sim)


def run_demo(
    backend: str,
    axes: int,
    cycles: int,
    rate_hz: float,
    *,
    status: bool = False,
    rt: RtState | None = None,
    logs: argparse.Namespace | None = None,
    delay_us: float = 0.0,
    motor: str = MOTORS[0],
) -> dict[str, Any]:
    """Run the demo; returns the report (``cycles``, ``missed``, ``safe_stops``, ``cycle_time_us``,
    ``latency_us``, ...). ``rt``: the real-time settings in force (reported); the histograms are under
    the private key ``_latency`` for a plot. ``logs``: parsed ``--can-log``/``--pcap``/``--record``/``--monitor`` flags.
    With ``rt`` from ``realtime(..., fifo_later=True)`` the cycle takes its priority after the set-up and before
    the bring-up, and the threads the set-up made (an in-process emulator's) take the same."""
    before = set(thread_ids())
    with (
        tempfile.TemporaryDirectory(prefix="fieldbus-demo-") as tmp,
        demo_network(backend, axes, rate_hz, Path(tmp), delay_us=delay_us, motor=motor) as setup,
        open_network(
            setup.net_file,
            backend=setup.backend,
            bus_options=buslogs.bus_options(logs, load_network(setup.net_file), setup.backend)
            if logs
            else None,
        ) as net,
    ):
        if rt is not None:
            cycleopts.cycle_priority(rt, before, others_below=0)
        op = net.bring_up()
        if logs is not None:
            cycleopts.start_recording(op, logs)  # --record
        follower = _follower(op, backend, axes, rate_hz, motor)
        timer, latency = cycleopts.run_timed(
            op,
            follower.step,
            1e6 / rate_hz,
            cycles,
            status=status,
            describe=follower.status,
            monitor=bool(getattr(logs, "monitor", False)),
        )
        report = run_report(op, timer, 1e6 / rate_hz)
        report.update(follower.summary())
        report.update(cycleopts.latency_report(latency, rt or RtState()))
        report["_latency"] = latency
        if backend == "rawcan":  # faults the motors reported, by name (e.g. a Damiao's own CAN timeout)
            report["motor_faults"] = [str(f) for f in net.backends[0].faults]
    report["backend"] = backend
    report["axes"] = axes
    if backend == "rawcan":
        report["motor"] = motor
    return report


def _follower(
    op: Operational, backend: str, axes: int, rate_hz: float, motor: str
) -> SineFollower | MitFollower | PositionFollower | SpeedFollower:
    """The demo's job for the backend: CiA 402 joints; MIT-mode motors (families mit, damiao, cubemars MIT);
    motors with their own position loop (ODrive in turns, CubeMars servo in position-speed)."""
    if backend != "rawcan":
        return SineFollower(op, axes, rate_hz)
    outputs = op["joints"].outputs.names
    if "kp" in outputs:
        return MitFollower(op, axes, rate_hz)
    if "speed_limit" in outputs:  # CubeMars servo: its position-speed packet (the map's mode)
        return PositionFollower(op, axes, rate_hz, per_rad=1.0, setup={"speed_limit": SERVO_SPEED_LIMIT})
    if "position" not in outputs and "velocity" in outputs:  # a wheel: speed commands, position read
        return SpeedFollower(op, axes, rate_hz)
    return PositionFollower(op, axes, rate_hz, per_rad=1.0 / (2 * math.pi), velocity_ff=True)  # ODrive: turns


class TrackingError:
    """Running max and RMS of |actual - target sent one cycle earlier| over all axes (rad); no allocation."""

    def __init__(self, axes: int) -> None:
        self.err = np.zeros(axes)
        self.max_rad = 0.0
        self.sum_sq = 0.0
        self.samples = 0

    def add(self, actual: Any, target: Any) -> None:
        np.subtract(actual, target, out=self.err)
        np.abs(self.err, out=self.err)
        self.max_rad = max(self.max_rad, float(self.err.max()))
        self.sum_sq += float(np.dot(self.err, self.err))
        self.samples += self.err.size

    def to_json(self) -> dict[str, Any]:
        rms = math.sqrt(self.sum_sq / self.samples) if self.samples else 0.0
        return {"max_rad": self.max_rad, "rms_rad": rms, "samples": self.samples}


class _SineJob:
    """What both followers share: the trajectory ``start + A (1 - cos 2 pi f t)`` and its tracking error."""

    def __init__(self, op: Operational, axes: int, rate_hz: float, group: str) -> None:
        self.op = op
        img = op[group]
        self.out, self.inp = img.outputs, img.inputs
        self.dt = 1.0 / rate_hz
        self.n = axes
        self.start = np.zeros(axes)
        self.prev_target = np.zeros(axes)
        self.tracking = TrackingError(axes)
        self.enabled_at: int | None = None
        self.k = 0

    def begin(self, k: int, position: Any, target: Any) -> None:
        """Every axis ready at cycle ``k``: the trajectory starts where the joints are."""
        self.enabled_at = k
        self.start[:] = position
        target[:] = position
        self.prev_target[:] = position

    def advance(self, k: int, target: Any) -> float:
        """Write this cycle's target (rad); returns the trajectory's velocity (rad/s)."""
        assert self.enabled_at is not None
        w = 2 * math.pi * FREQUENCY_HZ
        t = (k - self.enabled_at) * self.dt
        np.add(self.start, AMPLITUDE_RAD * (1.0 - math.cos(w * t)), out=target)
        self.prev_target[:] = target
        return AMPLITUDE_RAD * w * math.sin(w * t)

    def status(self) -> str:
        return f"max error {self.tracking.max_rad * 1e3:.2f} mrad"

    def summary(self) -> dict[str, Any]:
        return {
            "enabled": self.enabled_at is not None,
            "enable_cycles": self.enabled_at if self.enabled_at is not None else self.k + 1,
            "tracking_error": self.tracking.to_json(),
            "states": self.states(),
        }

    def states(self) -> list[str]:
        return []


class SineFollower(_SineJob):
    """Enable every joint through CiA 402, then follow ``start + A (1 - cos 2 pi f t)`` in CSP.

    Tracking error is the actual position minus the target sent one cycle
    earlier (the newest target the drive can have acted on), in rad, over the
    cycles after every joint is enabled.
    """

    def __init__(self, op: Operational, axes: int, rate_hz: float, group: str = "joints") -> None:
        super().__init__(op, axes, rate_hz, group)
        self.statusword = self.inp["statusword"]
        self.controlword = self.out["controlword"]
        self.position = self.inp["position_actual_value"]
        self.target = self.out["target_position"]
        self.mode = self.out["modes_of_operation"]
        self.mode_display = self.inp["modes_of_operation_display"]
        self.ctrl = Cia402Controller(axes, mode=Mode.CSP, timeout_cycles=int(ENABLE_TIMEOUT_S * rate_hz))
        self.ctrl.set_goal(Goal.ENABLE)

    def step(self, k: int) -> bool:
        self.k = k
        res = self.op.exchange()
        if not res.fresh or res.safe_stop:
            return False  # hold outputs; the policy counts the miss and escalates
        self.ctrl.step(self.statusword, self.controlword, self.mode_display, self.mode)
        if self.enabled_at is None:
            self.target[:] = self.position  # follow the joint while enabling: no jump on enable
            if self.ctrl.all_reached:
                self.begin(k, self.position, self.target)
            return False
        self.tracking.add(self.position, self.prev_target)
        self.advance(k, self.target)
        return False

    def status(self) -> str:
        if self.enabled_at is None:
            return f"enabling ({int(self.ctrl.reached.sum())}/{self.ctrl.n_axes})"
        return super().status()

    def states(self) -> list[str]:
        return [State402(int(s)).name if s >= 0 else "UNKNOWN" for s in self.ctrl.state]


class MitFollower(_SineJob):
    """MIT-mode motors: impedance control (kp, kd) towards ``start + A (1 - cos 2 pi f t)``.

    The motors are in motor mode from bring-up (``op()`` sends enter-motor-mode);
    "enabled" means every motor answered. Tracking error as in :class:`SineFollower`.
    """

    KP, KD = 40.0, 1.5  # N·m/rad, N·m·s/rad

    def __init__(self, op: Operational, axes: int, rate_hz: float, group: str = "joints") -> None:
        super().__init__(op, axes, rate_hz, group)
        self.position = self.inp["position"]
        self.target = self.out["position"]
        self.velocity = self.out["velocity"]  # feed-forward: the trajectory's velocity, rad/s
        self.out["kp"][:] = self.KP
        self.out["kd"][:] = self.KD

    def step(self, k: int) -> bool:
        self.k = k
        res = self.op.exchange()
        if not res.fresh or res.safe_stop:
            return False
        if self.enabled_at is None:
            self.begin(k, self.position, self.target)
            return False
        if k - self.enabled_at > 1:
            self.tracking.add(self.position, self.prev_target)
        self.velocity.fill(self.advance(k, self.target))
        return False

    def states(self) -> list[str]:
        return ["MOTOR_MODE" if self.enabled_at is not None else "NO_REPLY"] * self.n


class SpeedFollower(_SineJob):
    """Motors commanded in speed only (a wheel drive): the trajectory's velocity plus ``GAIN`` (1/s) times
    the position error, towards ``start + A (1 - cos 2 pi f t)``; tracking error in rad as the others."""

    GAIN = 10.0

    def __init__(self, op: Operational, axes: int, rate_hz: float, group: str = "joints") -> None:
        super().__init__(op, axes, rate_hz, group)
        self.position = self.inp["position"]
        self.speed = self.out["velocity"]
        self.goal = np.zeros(axes)  # this cycle's target, rad
        self.err = np.zeros(axes)

    def step(self, k: int) -> bool:
        self.k = k
        res = self.op.exchange()
        if not res.fresh or res.safe_stop:
            return False
        if self.enabled_at is None:
            self.begin(k, self.position, self.goal)
            return False
        if k - self.enabled_at > 1:
            self.tracking.add(self.position, self.prev_target)
        v = self.advance(k, self.goal)
        np.subtract(self.goal, self.position, out=self.err)
        np.multiply(self.err, self.GAIN, out=self.err)
        np.add(self.err, v, out=self.speed)
        return False

    def states(self) -> list[str]:
        return ["ANSWERING" if self.enabled_at is not None else "NO_REPLY"] * self.n


class PositionFollower(_SineJob):
    """Motors with their own position loop: the target position each cycle, in the map's unit
    (``per_rad`` units per rad: 1 for rad, 1/2 pi for ODrive's turns), with the trajectory's velocity as
    feed-forward when ``velocity_ff``; ``setup``: outputs written once (e.g. a speed limit).

    "Enabled" means every motor answered; tracking error as in :class:`SineFollower`, in rad.
    """

    def __init__(
        self,
        op: Operational,
        axes: int,
        rate_hz: float,
        *,
        per_rad: float,
        setup: dict[str, float] | None = None,
        velocity_ff: bool = False,
        group: str = "joints",
    ) -> None:
        super().__init__(op, axes, rate_hz, group)
        self.per_rad = per_rad
        self.position = self.inp["position"]
        self.target = self.out["position"]
        self.ff = self.out["velocity"] if velocity_ff else None
        self.rad = np.zeros(axes)  # the positions read, rad
        self.goal = np.zeros(axes)  # this cycle's target, rad
        for name, value in (setup or {}).items():
            self.out[name][:] = value

    def step(self, k: int) -> bool:
        self.k = k
        res = self.op.exchange()
        if not res.fresh or res.safe_stop:
            return False
        np.divide(self.position, self.per_rad, out=self.rad)
        if self.enabled_at is None:
            self.begin(k, self.rad, self.goal)
        else:
            if k - self.enabled_at > 1:
                self.tracking.add(self.rad, self.prev_target)
            v = self.advance(k, self.goal)
            if self.ff is not None:
                self.ff.fill(v * self.per_rad)
        np.multiply(self.goal, self.per_rad, out=self.target)
        return False

    def states(self) -> list[str]:
        return ["ANSWERING" if self.enabled_at is not None else "NO_REPLY"] * self.n
