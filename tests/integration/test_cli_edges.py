"""The CLI's rough edges (issue 28), each as a user meets it: the ``fieldbus`` command in a subprocess.

Every error is an exit code and one line on stderr, never a traceback: a reader that closes stdout
early (141, quiet), output paths checked before anything runs (1), numbers refused by argparse (2),
Ctrl-C (130, drives stopped), ``--json`` errors as JSON, exit codes in every ``--help``.

What is decided before a command runs (numbers argparse refuses, ``--help`` texts, output paths
checked first) is checked in this process through ``fieldbus.cli.main`` (:func:`in_process`: the
same exit code, stdout and stderr, without a subprocess that imports everything again). A real
``fieldbus`` process still proves each path reaches the shell: ``--json`` errors (argparse's 2, a
:class:`~fieldbus.errors.FieldbusError`'s 1), a refused plot format (1), the limits of dc-sim and
the CAN demo (2).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import suppress
from pathlib import Path
from typing import Any
from unittest.mock import patch

import pytest

from fieldbus.cli import build_parser, main

REPO = Path(__file__).resolve().parents[2]
MAPS = sorted((REPO / "pdo_maps").glob("*.yaml"))
DEMO_NET = REPO / "examples" / "demo_network.yaml"
CAN_NET = REPO / "examples" / "demo_canopen.yaml"
EASYCAT = REPO / "tests" / "data" / "esi" / "abt_easycat_v2_0.xml"
SAMPLE_EDS = REPO / "tests" / "data" / "eds" / "canopen_sample.eds"
FOREVER = "100000000"  # cycles: a command that got this far before its check would not finish in the test


def _env() -> dict[str, str]:
    """The code beside this test, whatever is installed."""
    return {
        **os.environ,
        "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")])),
    }


def fieldbus(*args: str | Path, stdout: Any = subprocess.PIPE) -> subprocess.CompletedProcess[str]:
    """``fieldbus ARGS`` in a subprocess (stdout and stderr captured, or stdout to ``stdout``)."""
    cmd = [sys.executable, "-m", "fieldbus", *map(str, args)]
    return subprocess.run(cmd, stdout=stdout, stderr=subprocess.PIPE, text=True, env=_env(), timeout=300)


def in_process(capsys: pytest.CaptureFixture[str], *args: str | Path) -> subprocess.CompletedProcess[str]:
    """``fieldbus ARGS`` through ``fieldbus.cli.main`` in this process, as :func:`fieldbus` reports it:
    the exit code (``main``'s return or its ``SystemExit``), stdout and stderr. For command lines
    refused before the command does anything."""
    capsys.readouterr()
    argv = list(map(str, args))
    # help as wide as a subprocess writing to a pipe formats it (80 columns unless COLUMNS says)
    columns = os.environ.get("COLUMNS", "80")
    try:
        with patch.dict(os.environ, {"COLUMNS": columns}):
            code = main(argv)
    except SystemExit as exc:  # argparse: --help, a refused command line
        code = 0 if exc.code is None else exc.code if isinstance(exc.code, int) else 1
    out = capsys.readouterr()
    return subprocess.CompletedProcess(["fieldbus", *argv], code, out.out, out.err)


def one_line_error(res: subprocess.CompletedProcess[str], code: int, *needles: str) -> str:
    """``res`` exited ``code`` with exactly one line on stderr holding every needle, and no traceback."""
    assert "Traceback" not in res.stderr + res.stdout, res.stderr
    lines = res.stderr.strip().splitlines()
    assert res.returncode == code and len(lines) == 1, (res.returncode, res.stderr)
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    return lines[0]


# -- 1. a reader that closes stdout early ---------------------------------------------------------
@pytest.fixture
def can_log(tmp_path: Path) -> Path:
    """A candump log of 3000 TPDO frames of the CANopen demo's nodes (about 280 KB decoded)."""
    path = tmp_path / "bus.log"
    lines = [
        f"({1000 + k * 0.001:.6f}) can0 {0x181 + k % 4:03X}#{k % 256:02X}00000000000000" for k in range(3000)
    ]
    path.write_text("\n".join(lines) + "\n")
    return path


def closed_reader(*args: str | Path) -> subprocess.CompletedProcess[str]:
    """Run with stdout a pipe whose reader has already gone (``| head -0``): the first write fails."""
    r, w = os.pipe()
    os.close(r)
    try:
        return fieldbus(*args, stdout=w)
    finally:
        os.close(w)


@pytest.mark.parametrize(
    "argv",
    [
        ["validate", *MAPS],
        ["dc-sim", "--json"],
        ["bandwidth", DEMO_NET, "--json"],
        ["import", "esi", EASYCAT, "--device", "0xDEFEDE64"],
        ["demo", "--axes", "1", "--cycles", "50", "--json"],
    ],
    ids=lambda a: a[0],
)
def test_a_closed_stdout_exits_141_quietly(argv: list[str]) -> None:
    res = closed_reader(*argv)
    assert res.returncode == 141 and "Traceback" not in res.stderr, res.stderr
    assert "Broken pipe" not in res.stderr and "Exception ignored" not in res.stderr


def test_decode_into_head(can_log: Path) -> None:
    """``fieldbus decode LOG | head -1``: the reader takes a line and goes; the rest is dropped, exit 141."""
    cmd = [sys.executable, "-m", "fieldbus", "decode", str(can_log), "--network", str(CAN_NET)]
    with subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=_env()) as proc:
        assert proc.stdout is not None and proc.stderr is not None
        first = proc.stdout.readline()
        proc.stdout.close()  # far more than a pipe holds is still to come
        err = proc.stderr.read()
        code = proc.wait(timeout=300)
    assert "TPDO1" in first
    assert code == 141 and err == "", err


@pytest.mark.veth
@pytest.mark.timeout(300)
@pytest.mark.usefixtures("generous_pysoem_timeouts")
def test_sdo_list_into_a_closed_pipe(ethercat_emulator: Any) -> None:
    emu = ethercat_emulator([REPO / "pdo_maps" / "generic_cia402.yaml"], app="none")
    res = closed_reader("sdo", "list", "ethercat", emu.iface, "--slave", "0")
    assert res.returncode == 141 and "Traceback" not in res.stderr, res.stderr


# -- 2. output paths checked before anything runs --------------------------------------------------
@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("rec") / "demo.mcap"
    res = fieldbus("demo", "--axes", "1", "--cycles", "50", "--json", "--record", path)
    assert res.returncode == 0, res.stderr
    return path


BAD_OUTPUTS = {
    "missing folder": lambda tmp: tmp / "no" / "such" / "out.png",
    "a folder": lambda tmp: tmp,
    "/proc": lambda tmp: Path("/proc/fieldbus-cli-edges.png"),
}


@pytest.mark.parametrize("kind", list(BAD_OUTPUTS))
@pytest.mark.parametrize(
    "command",
    ["bandwidth --plot", "dc-sim --plot", "demo --plot", "run --plot", "plot -o", "import esi -o"],
)
def test_an_output_that_cannot_be_written_is_refused_before_the_run(
    command: str, kind: str, tmp_path: Path, recording: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = BAD_OUTPUTS[kind](tmp_path)
    if command.startswith("import"):
        out = out.with_suffix(".yaml") if out != tmp_path else out
    flag = command.split()[-1]
    argv: dict[str, list[str | Path]] = {
        "bandwidth --plot": ["bandwidth", DEMO_NET],
        "dc-sim --plot": ["dc-sim", "--seconds", "100"],
        "demo --plot": ["demo", "--cycles", FOREVER],
        "run --plot": ["run", DEMO_NET, "--backend", "sim", "--cycles", FOREVER],
        "plot -o": ["plot", recording],
        "import esi -o": ["import", "esi", EASYCAT, "--device", "0xDEFEDE64"],
    }
    res = in_process(capsys, *argv[command], flag, out)
    one_line_error(res, 1, f"{flag} {out}")


@pytest.mark.parametrize("bus", ["ethercat", "canopen"])
@pytest.mark.parametrize("kind", ["a file", "/proc"])
def test_scan_write_maps_checks_its_folder_before_scanning(
    bus: str, kind: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    target = tmp_path / "maps.txt" if kind == "a file" else Path("/proc/fieldbus-cli-edges")
    if kind == "a file":
        target.write_text("not a folder\n")
    where = ["fieldbus-no-such-nic"] if bus == "ethercat" else ["no-such-channel", "--interface", "virtual"]
    res = in_process(capsys, "scan", bus, *where, "--write-maps", target)
    one_line_error(res, 1, f"--write-maps {target}")


def test_a_plot_format_matplotlib_cannot_write_is_refused(tmp_path: Path) -> None:
    """In a real ``fieldbus`` process: a refused output path exits 1 there too."""
    res = fieldbus("dc-sim", "--plot", tmp_path / "spread.xyz")
    one_line_error(res, 1, "--plot", "cannot write .xyz files", ".png")


# -- 3. numbers argparse refuses ------------------------------------------------------------------
@pytest.mark.parametrize(
    "argv",
    [
        ["demo", "--rate", "nan"],
        ["demo", "--rate", "inf"],
        ["demo", "--rate", "-5"],
        ["demo", "--cycles", "0"],
        ["soak", "--demo", "--cycles", "100", "--rate", "nan"],
        ["soak", "--demo", "--cycles", "100", "--rate", "inf"],
        ["soak", "--demo", "--cycles", "100", "--margin-us", "nan"],
        ["soak", "--demo", "--cycles", "100", "--margin-us", "inf"],
        ["soak", "--demo", "--cycles", "100", "--seed", "-1"],
        ["latency", DEMO_NET, "--backend", "sim", "--steps", "1", "--step", "nan"],
        ["latency", DEMO_NET, "--backend", "sim", "--steps", "1", "--step", "-0.1"],
        ["run", DEMO_NET, "--backend", "sim", "--cycles", "-1"],
        ["dc-sim", "--drift-ppm", "nan"],
        ["dc-sim", "--seed", "-1"],
    ],
    ids=lambda argv: " ".join(a.name if isinstance(a, Path) else a for a in argv),
)
def test_meaningless_numbers_are_refused_by_argparse(
    argv: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    flag = next(a for a in reversed(argv) if str(a).startswith("--"))
    one_line_error(in_process(capsys, *argv), 2, f"argument {flag}", f"'{argv[-1]}'")


def test_dc_sim_refuses_a_run_larger_than_its_limit_naming_it() -> None:
    line = one_line_error(fieldbus("dc-sim", "--seconds", "1e9"), 2, "--seconds", "limit is 1e+07")
    assert "at most 1250 s" in line  # 8 slaves at 1 ms


def test_a_can_demo_refuses_more_axes_than_node_ids() -> None:
    one_line_error(fieldbus("demo", "--backend", "canopen", "--axes", "200"), 2, "at most 127 axes")


# -- 4. Ctrl-C ------------------------------------------------------------------------------------
@pytest.fixture
def interrupted() -> Iterator[Any]:
    """``run(argv, record)``: start fieldbus in its own session, wait until the recording has begun
    (``--record`` creates the file empty and writes its header once the network is in OP), then
    Ctrl-C as a terminal sends it (SIGINT to the foreground process group); returns (exit code, stderr)."""
    procs: list[subprocess.Popen[str]] = []

    def run(argv: list[str | Path], record: Path) -> tuple[int, str]:
        cmd = [sys.executable, "-m", "fieldbus", *map(str, argv), "--record", str(record)]
        env = {**_env(), "PYTHONFAULTHANDLER": "1"}  # SIGABRT then prints every thread's stack
        proc = subprocess.Popen(
            cmd,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
            start_new_session=True,
            preexec_fn=_sigint_by_default,
        )
        procs.append(proc)
        deadline = time.monotonic() + 240  # a safety net for a broken bring-up, not a timing bound
        while not (record.exists() and record.stat().st_size > 0):
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, "no cycles recorded"
            time.sleep(0.05)
        time.sleep(1.0)  # let it cycle a while (drives enabled, faults injected); nothing depends on how long
        os.killpg(proc.pid, signal.SIGINT)
        try:
            _, err = proc.communicate(timeout=240)
        except subprocess.TimeoutExpired:  # not stopped: where each of its threads is, before it is killed
            os.kill(proc.pid, signal.SIGABRT)
            _, err = proc.communicate(timeout=60)
            pytest.fail(f"still running 240 s after SIGINT; its threads at SIGABRT:\n{err[-8000:]}")
        return proc.returncode, err

    yield run
    for proc in procs:  # a failed test: the command and its children (the emulator has its own group)
        if proc.poll() is None:
            for pid in [proc.pid, *_descendants(proc.pid)]:
                with suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGKILL)
            proc.wait()


def _sigint_by_default() -> None:
    """In the child before it runs fieldbus: SIGINT to its default, as for a terminal's foreground job.

    A suite started in the background by a non-interactive shell (``cmd &``, ``nohup cmd &``) has SIGINT
    ignored, every process below it inherits that, and Python keeps an inherited SIG_IGN: the command
    would never see the Ctrl-C this fixture sends (beside two burners, started with ``nohup``, both soak
    tests waited 240 s)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _descendants(pid: int) -> list[int]:
    """Every process below ``pid`` (from /proc)."""
    children: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            ppid = int(stat.read_text().rsplit(")", 1)[1].split()[1])
        except (OSError, IndexError, ValueError):
            continue
        children.setdefault(ppid, []).append(int(stat.parent.name))
    found, todo = [], [pid]
    while todo:
        for child in children.get(todo.pop(), []):
            found.append(child)
            todo.append(child)
    return found


def test_ctrl_c_in_a_soak_stops_the_drives_and_exits_130(interrupted: Any, tmp_path: Path) -> None:
    code, err = interrupted(["soak", "--demo", "--axes", "2", "--cycles", FOREVER], tmp_path / "soak.mcap")
    lines = err.strip().splitlines()
    assert "Traceback" not in err and code == 130 and len(lines) == 1, (code, err)
    # what the emulated drives say after the master closed: no drive enabled, every slave in INIT
    assert lines[0].startswith("interrupted: after ") and "drives stopped" in lines[0], lines[0]
    assert "every slave in INIT (the emulator's status)" in lines[0]


@pytest.mark.veth
@pytest.mark.timeout(600)
def test_ctrl_c_in_a_soak_over_veth_stops_the_drives_and_exits_130(
    interrupted: Any, tmp_path: Path, veth_possible: None
) -> None:
    """The emulator is a child process: the terminal's Ctrl-C must not reach it before the master
    has stopped the drives through it."""
    argv = ["soak", "--demo", "--backend", "ethercat", "--axes", "2", "--cycles", FOREVER]
    code, err = interrupted(argv, tmp_path / "soak.mcap")
    lines = err.strip().splitlines()
    assert "Traceback" not in err and code == 130 and len(lines) == 1, (code, err)
    assert "drives stopped" in lines[0] and "every slave in INIT (the emulator's status)" in lines[0]


# -- 5. help texts --------------------------------------------------------------------------------
def _parsers(
    parser: argparse.ArgumentParser, path: tuple[str, ...] = ()
) -> Iterator[tuple[str, argparse.ArgumentParser]]:
    yield " ".join(("fieldbus", *path)), parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _parsers(sub, (*path, name))


PARSERS = dict(_parsers(build_parser()))


@pytest.mark.parametrize("command", sorted(PARSERS))
def test_every_help_lists_exit_codes_and_explains_every_option(command: str) -> None:
    parser = PARSERS[command]
    text = parser.format_help()
    assert "\nexit codes:\n" in text, command
    codes = {
        int(line.split()[0])
        for line in text.split("\nexit codes:\n")[1].splitlines()
        if line[:3].strip().isdigit()
    }
    assert {0, 1, 2, 130, 141} <= codes, (command, codes)
    assert "``" not in text and ":mod:" not in text and "fieldbus.commands" not in text, text
    for action in parser._actions:
        if not isinstance(
            action, argparse._HelpAction | argparse._VersionAction | argparse._SubParsersAction
        ):
            assert action.help, (command, action.option_strings or action.dest)


@pytest.mark.parametrize("command", ["scan", "sdo", "run", "latency"])
def test_help_starts_with_a_sentence(command: str, capsys: pytest.CaptureFixture[str]) -> None:
    res = in_process(capsys, command, "--help")
    assert res.returncode == 0
    description = res.stdout.split("\n\n")[1]
    assert "`" not in description and description.startswith(f"fieldbus {command} "), description


def test_top_level_help_speaks_to_users(capsys: pytest.CaptureFixture[str]) -> None:
    res = in_process(capsys, "--help")
    assert res.returncode == 0 and "exit codes:" in res.stdout
    assert "module" not in res.stdout and "fieldbus.commands" not in res.stdout


def test_soak_explains_cycles_and_seed(capsys: pytest.CaptureFixture[str]) -> None:
    text = " ".join(in_process(capsys, "soak", "--help").stdout.split())
    assert "--cycles CYCLES cycles to run under the fault plan" in text
    assert "--seed SEED seed of the fault plan" in text


# -- 6. warnings and --json errors ---------------------------------------------------------------
def test_import_says_a_repeated_warning_once_with_a_count(tmp_path: Path) -> None:
    res = fieldbus("import", "esi", EASYCAT, "--device", "0xDEFEDE64", "-o", tmp_path / "easycat.yaml")
    assert res.returncode == 0, res.stderr
    dummy = [line for line in res.stderr.splitlines() if "dummy object" in line]
    # 64 output and 64 input bytes, each mapped at a CiA 301 dummy object: 128 alike warnings
    assert len(dummy) == 1 and "and 127 more alike" in dummy[0], res.stderr


def test_eds_import_routes_the_canopen_packages_log_through_our_warnings(tmp_path: Path) -> None:
    res = fieldbus("import", "eds", SAMPLE_EDS, "-o", tmp_path / "sample.yaml")
    assert res.returncode == 0, res.stderr
    lines = res.stderr.strip().splitlines()
    assert lines and all(line.startswith("warning: ") for line in lines), lines
    assert any(line.startswith("warning: canopen, reading ") and "(0x40)" in line for line in lines), lines


@pytest.mark.parametrize(
    ("argv", "code", "needle"),
    [
        (["bandwidth", "no-such-network.yaml", "--json"], 1, "no-such-network.yaml"),
        (["demo", "--json", "--rate", "nan"], 2, "argument --rate"),
        (["dc-sim", "--json", "--seconds", "1e9"], 2, "limit is 1e+07"),
    ],
)
def test_json_errors_are_json_on_stdout_too(argv: list[str], code: int, needle: str) -> None:
    res = fieldbus(*argv)
    one_line_error(res, code, needle)
    out = json.loads(res.stdout)
    assert out["ok"] is False and out["exit"] == code and needle in out["error"], out


# -- 7. the demo's generated network --------------------------------------------------------------
def test_an_error_in_the_demos_generated_network_does_not_name_a_temporary_file() -> None:
    # 2 s of command delay is 2000 cycles at 1 kHz: more than the emulator takes
    res = fieldbus("demo", "--axes", "1", "--cycles", "10", "--delay-us", "2e6")
    line = one_line_error(res, 1, "the demo's generated network", "emulator.command_delay_us")
    assert "fieldbus-demo-" not in line and ".yaml" not in line, line


# -- 8. scripts/test and apt ----------------------------------------------------------------------
@pytest.mark.parametrize("opt_out", [False, True])
def test_scripts_test_says_it_installs_with_apt_and_can_be_told_not_to(tmp_path: Path, opt_out: bool) -> None:
    """scripts/test in a copy whose tools are stand-ins: root, apt-get there, tshark not."""
    (tmp_path / "scripts").mkdir()
    script = tmp_path / "scripts" / "test"
    script.write_text((REPO / "scripts" / "test").read_text())
    bin_dir, venv = tmp_path / "bin", tmp_path / ".venv" / "bin"
    bin_dir.mkdir()
    venv.mkdir(parents=True)
    log = tmp_path / "calls"
    stubs = {
        bin_dir / "id": "echo 0",
        bin_dir / "apt-get": f'echo "apt-get $*" >> {log}; echo "APT-GET-RAN" >&2',
        bin_dir / "debconf-set-selections": "while read -r _; do :; done",
        **{
            venv / tool: f'echo "{tool}" >> {log}'
            for tool in ("fieldbus", "python", "ruff", "mypy", "pytest")
        },
    }
    for path, body in stubs.items():
        path.write_text(f"#!/bin/sh\n{body}\n")
        path.chmod(0o755)
    (bin_dir / "dirname").symlink_to(
        subprocess.run(["sh", "-c", "command -v dirname"], capture_output=True, text=True).stdout.strip()
    )
    env = {"PATH": str(bin_dir), "HOME": str(tmp_path), **({"FIELDBUS_NO_APT": "1"} if opt_out else {})}
    res = subprocess.run(["/bin/bash", str(script)], capture_output=True, text=True, env=env, timeout=60)
    assert res.returncode == 0, res.stderr
    calls = log.read_text().splitlines()
    assert calls[-1] == "pytest"  # the suite still runs
    if opt_out:
        assert not any(c.startswith("apt-get") for c in calls) and "apt-get" not in res.stderr, res.stderr
    else:
        assert "apt-get install -y -qq tshark iproute2" in calls
        said = res.stderr.splitlines()
        assert "installing tshark and iproute2 with apt-get" in said[0] and "FIELDBUS_NO_APT=1" in said[0]
        assert said.index("APT-GET-RAN") > 0  # said before apt-get ran


def test_sigterm_stops_the_drives_like_ctrl_c_and_exits_143(tmp_path: Path) -> None:
    """SIGTERM (systemd, docker stop, kill) unwinds as Ctrl-C does: controlled stop, buses closed, exit 143."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "fieldbus.cli", "demo", "--backend", "sim", "--cycles", "1000000"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=tmp_path,
    )
    time.sleep(3.0)  # bring-up and some cycles (a SIGTERM during bring-up must end the same way)
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 143, (out, err)
    assert "terminated (SIGTERM): drives stopped, buses closed" in err and "Traceback" not in err
