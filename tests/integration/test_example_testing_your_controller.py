"""The worked example of docs/testing.md runs: its own pytest file, in a subprocess, as a user runs it.

It imports only ``fieldbus`` and ``fieldbus.testing`` (checked here), finds the
``fieldbus_emulation`` fixture through the installed pytest plugin, and its
veth cases skip only where the machine refuses a veth pair.
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("can")

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "testing_your_controller"

pytestmark = [pytest.mark.slow, pytest.mark.timeout(600)]


def test_the_example_uses_the_public_api_only() -> None:
    for f in EXAMPLE.glob("*.py"):
        for line in f.read_text().splitlines():
            m = re.match(r"\s*(?:from|import) ([\w.]+)", line)
            if m and (
                m.group(1).startswith(("fieldbus.", "sim_slaves")) and m.group(1) != "fieldbus.testing"
            ):
                pytest.fail(f"{f.name}: {line.strip()}")


def test_the_example_suite_passes() -> None:
    res = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-rs", "-p", "no:cacheprovider", str(EXAMPLE)],
        cwd=EXAMPLE,
        capture_output=True,
        text=True,
        check=False,
    )
    out = res.stdout + res.stderr
    assert res.returncode == 0, out[-4000:]
    summary = out.strip().splitlines()[-1]
    assert re.search(r"\b12 passed\b", summary) or (
        "skipped" in summary and "veth" in out and "passed" in summary
    ), summary
