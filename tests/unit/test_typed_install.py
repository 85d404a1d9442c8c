"""A user's own code type-checks against the installed fieldbus (the README's editable install, py.typed)."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest


def test_mypy_sees_fieldbus_from_a_folder_outside_the_checkout(tmp_path: Path) -> None:
    if shutil.which("mypy") is None and not (Path(sys.executable).parent / "mypy").exists():
        pytest.skip("mypy is not installed (the dev extra brings it)")
    user = tmp_path / "my_controller.py"
    user.write_text(
        "import fieldbus\n\n"
        "def cycle(op: fieldbus.Operational) -> bool:\n"
        "    return op.exchange().fresh\n\n"
        "wrong: int = fieldbus.open_network\n"
    )
    out = subprocess.run(
        [sys.executable, "-m", "mypy", "--no-incremental", str(user)],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=300,
    )
    # found and checked: the one error is the deliberate one, not "Cannot find implementation"
    assert "import-not-found" not in out.stdout, out.stdout
    assert "my_controller.py:6: error: Incompatible types in assignment" in out.stdout, out.stdout
