"""The hostile-input corpus (tests/data/hostile/) against every command that reads a file.

Each file of the corpus, and a few made here (a directory, a symbolic-link loop,
a FIFO, a sparse file past the size limit), goes to validate, bandwidth,
run --cycles 1 on sim, soak, latency, decode (as the network and as the log),
import esi / eds and report / plot. Every command must end with exit 0, or with
a non-zero exit and one ``error:`` line; never an uncaught exception (the
traceback a user would see) and never the fake secret some files hold. The
commands run in-process through ``fieldbus.cli.main`` (an exception escaping it
is what the console script prints as a traceback); the secret cases also run
as real subprocesses for validate, run and bandwidth.

Only our own code judges here: the oracle is the rule itself (exit code, one
line, no secret), not another parser.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

from fieldbus.cli import main

REPO = Path(__file__).resolve().parents[2]
CORPUS = REPO / "tests" / "data" / "hostile"
SECRET = "FAKE-SECRET-d41d8cd98f00b204e9800998ecf8427e"
SECRET_PART = SECRET[12:20]  # no 8 characters of the secret's hex, where a file is no map of ours
# Files that look like a drive map or network file and hold the secret in a key: there a key may be
# quoted up to its first 32 name characters (never the whole secret).
MAP_LIKE_SECRETS = {"secret_key_in_map.yaml", "secret_key_in_network.yaml", "net_map_secret_key.yaml"}
DEMO_CAN = REPO / "examples" / "demo_canopen.yaml"

Argv = Callable[[str, Path], list[str]]
COMMANDS: dict[str, Argv] = {
    "validate": lambda f, out: ["validate", f],
    "validate-json": lambda f, out: ["validate", "--json", f],
    "bandwidth": lambda f, out: ["bandwidth", f],
    "register": lambda f, out: ["register", f, "arm", "j0", "PMAX"],
    "run": lambda f, out: ["run", f, "--cycles", "1", "--backend", "sim"],
    "soak": lambda f, out: ["soak", f, "--cycles", "1", "--rate", "0"],
    "latency": lambda f, out: ["latency", f, "--backend", "sim", "--steps", "1", "--hold", "4"],
    "decode-network": lambda f, out: ["decode", str(CORPUS / "decode.log"), "--network", f],
    "decode-log": lambda f, out: ["decode", f, "--network", str(DEMO_CAN)],
    "import-esi": lambda f, out: ["import", "esi", f, "-o", str(out / "esi.yaml")],
    "import-eds": lambda f, out: ["import", "eds", f, "-o", str(out / "eds.yaml")],
    "report": lambda f, out: ["report", f],
    "plot": lambda f, out: ["plot", f, "-o", str(out / "plot.png")],
    "eeprom-decode": lambda f, out: ["eeprom", "decode", f],
    "eeprom-decode-json": lambda f, out: ["eeprom", "decode", "--json", f],
}
# Commands that read the file as given whatever its name ends in; import eds and esi also get a copy
# named .eds / .xml, so the content reaches the parser.
RENAMED = {"import-eds": ".eds", "import-esi": ".xml", "report": ".mcap", "plot": ".mcap"}


def corpus_files() -> list[str]:
    return sorted(p.name for p in CORPUS.iterdir() if p.is_file() and p.name != "README.md")


def _check(name: str, code: object, out: str, err: str) -> None:
    """The rule: exit 0 or 3, or another code with one ``error:`` line (``--json``: or one JSON object saying
    ``ok: false``); no traceback; no secret."""
    text = out + err
    assert SECRET not in text, (name, text[:500])
    if name not in MAP_LIKE_SECRETS:
        assert SECRET_PART not in text, (name, text[:500])
    assert "Traceback" not in text, (name, text[:500])
    if code not in (0, 3):  # 3: the command ran and its own check failed (e.g. latency's measurement)
        lines = [line for line in err.splitlines() if line.strip() and not line.startswith("warning: ")]
        if not lines and out.startswith("{"):
            assert out.count("\n") == 1 and json.loads(out)["ok"] is False, (name, out[:800])
            return
        assert len(lines) == 1 and lines[0].startswith("error: "), (name, code, err[:800])


def _run_main(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[object, str, str]:
    try:
        code: object = main(argv)
    except SystemExit as exc:  # argparse: usage errors exit 2 with one line after the usage
        code = exc.code
    out = capsys.readouterr()
    return code, out.out, out.err


CASES = [(cmd, f) for cmd in COMMANDS for f in corpus_files()]


@pytest.mark.timeout(300)
@pytest.mark.parametrize(("command", "name"), CASES, ids=[f"{c}-{f}" for c, f in CASES])
def test_every_command_refuses_the_corpus_cleanly(
    command: str,
    name: str,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.chdir(CORPUS)  # relative names, as a user types them; maps resolve beside the network
    target = name
    if command in RENAMED:
        copy = tmp_path / (Path(name).stem + RENAMED[command])
        shutil.copyfile(CORPUS / name, copy)
        target = str(copy)
    code, out, err = _run_main(COMMANDS[command](target, tmp_path), capsys)
    if command in ("validate", "validate-json") and name in ("bom_map.yaml", "crlf_map.yaml"):
        assert code == 0, err  # valid maps with a BOM or CRLF line ends
    _check(name, code, out, err)


def test_an_eds_import_of_a_secret_quotes_none_of_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """configparser's own message quotes the file's first line: the EDS import names only its type."""
    copy = tmp_path / "shadow_like.eds"
    shutil.copyfile(CORPUS / "shadow_like", copy)
    code, _out, err = _run_main(COMMANDS["import-eds"](str(copy), tmp_path), capsys)
    assert code == 1 and "root:" not in err and err.count("\n") == 1, err


def _made_files(tmp_path: Path) -> dict[str, Path]:
    """Hostile paths that cannot live in the repository: a directory, a loop, a FIFO, a huge sparse file."""
    folder = tmp_path / "folder.yaml"
    folder.mkdir()
    loop = tmp_path / "loop.yaml"
    loop.symlink_to(loop)
    fifo = tmp_path / "fifo.yaml"
    os.mkfifo(fifo)
    huge = tmp_path / "huge.yaml"
    with huge.open("wb") as f:
        f.truncate(64 * 1024 * 1024)
    out = {"directory": folder, "symlink loop": loop, "fifo": fifo, "huge": huge}
    for what, path in list(out.items()):  # and each one named as a map by a network file
        net = tmp_path / f"net_{path.stem}.yaml"
        net.write_text(
            f"buses:\n  - {{name: b, type: ethercat, interface: eth0, slaves: [{{name: a, map: {path.name}}}]}}\n"
        )
        out[f"network naming a {what}"] = net
    return out


@pytest.mark.timeout(120)
@pytest.mark.parametrize("command", ["validate", "bandwidth", "run", "soak", "latency", "decode-network"])
def test_paths_that_are_no_file_are_refused_without_reading_them(
    command: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A FIFO would block a reader forever and the sparse file is 64 MiB: both are refused unread."""
    for what, path in _made_files(tmp_path).items():
        code, out, err = _run_main(COMMANDS[command](str(path), tmp_path), capsys)
        assert code == 1, (what, code, err)
        _check(what, code, out, err)


SECRET_LINE = f"root:$6${SECRET}:20228:0:99999:7:::\n"


@pytest.mark.parametrize("suffix", ["", ".yaml", ".txt"])
@pytest.mark.parametrize("command", ["validate", "run", "bandwidth"])
def test_a_map_path_never_prints_the_file_it_names(tmp_path: Path, command: str, suffix: str) -> None:
    """issue 28: ``map: /etc/shadow`` printed the file's first line. A real subprocess, as a user runs it."""
    secret = tmp_path / f"shadow{suffix}"
    secret.write_text(SECRET_LINE + "daemon:*:20228:0:99999:7:::\n")
    net = tmp_path / "net.yaml"
    net.write_text(
        "buses:\n  - name: b\n    type: ethercat\n    interface: eth0\n    slaves:\n"
        f"      - {{name: a, map: {secret}}}\n"
    )
    argv = {"validate": ["validate", str(net)], "bandwidth": ["bandwidth", str(net)]}.get(
        command, ["run", str(net), "--cycles", "1", "--backend", "sim"]
    )
    done = subprocess.run(
        [sys.executable, "-m", "fieldbus", *argv], capture_output=True, text=True, timeout=120, check=False
    )
    assert done.returncode == 1, done.stderr
    assert SECRET not in done.stdout + done.stderr and SECRET_PART not in done.stderr
    assert "root:$6$" not in done.stderr and "Traceback" not in done.stderr
    assert done.stderr.count("\n") == 1 and done.stderr.startswith(f"error: {net}:6:"), done.stderr


@pytest.mark.parametrize("command", ["validate", "run", "bandwidth"])
def test_the_file_itself_given_as_a_network_is_not_quoted(tmp_path: Path, command: str) -> None:
    secret = tmp_path / "shadow"
    secret.write_text(SECRET_LINE)
    extra = ["--cycles", "1", "--backend", "sim"] if command == "run" else []
    done = subprocess.run(
        [sys.executable, "-m", "fieldbus", command, str(secret), *extra],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert done.returncode == 1 and "Traceback" not in done.stderr
    assert SECRET_PART not in done.stdout + done.stderr and "root:$6$" not in done.stderr, done.stderr
    assert done.stderr.count("\n") == 1, done.stderr
