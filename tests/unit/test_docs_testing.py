"""The Python blocks of docs/testing.md run as written (from the repository root), public names only."""

from __future__ import annotations

import os
import re
from pathlib import Path

import pytest

pytest.importorskip("can")

ROOT = Path(__file__).resolve().parents[2]
TEXT = (ROOT / "docs" / "testing.md").read_text()
BLOCKS = re.findall(r"```python\n(.*?)```", TEXT, re.S)


def test_testing_doc_python_blocks_run(monkeypatch: pytest.MonkeyPatch) -> None:
    assert len(BLOCKS) >= 3
    monkeypatch.chdir(ROOT)
    for block in BLOCKS:
        namespace: dict[str, object] = {}
        exec(compile(block, "docs/testing.md", "exec"), namespace)
        tests = [f for name, f in namespace.items() if name.startswith("test_") and callable(f)]
        for test in tests:  # a pytest block: run it with the plugin's fixture, as pytest would
            from contextlib import ExitStack

            from fieldbus.testing import emulate

            with ExitStack() as stack:
                test(lambda net, **kw: stack.enter_context(emulate(net, **kw)))  # type: ignore[operator]
    assert os.getcwd() == str(ROOT)


def test_testing_doc_uses_the_public_names_only() -> None:
    imports = [ln.strip() for b in BLOCKS for ln in b.splitlines() if re.match(r"\s*(from|import) ", ln)]
    allowed = re.compile(r"(import (fieldbus|numpy as np)$|from fieldbus(\.testing)? import )")
    assert all(allowed.match(line) for line in imports), imports
