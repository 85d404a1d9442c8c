"""The repository stands alone: nothing it ships reads outside it or names a machine's path."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
# a path out of the checkout, or an absolute path of some machine's home, venv or work folder
OUTSIDE = re.compile(r"\.\./shared|\bshared/interop|/work/|/root/|/home/\w|/Users/\w|[A-Z]:\\\\Users")
TEXT = {".py", ".md", ".yaml", ".yml", ".toml", ".cfg", ".txt", ".c", ".sh", ""}


def _tracked() -> list[Path]:
    out = subprocess.run(
        ["git", "-C", str(REPO), "ls-files", "--cached", "--others", "--exclude-standard"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    return [
        REPO / line for line in out.splitlines() if (REPO / line).suffix in TEXT and (REPO / line).is_file()
    ]


def test_no_file_reads_outside_the_repository_or_names_a_machine_path() -> None:
    files = _tracked()
    assert len(files) > 100  # the listing really covers the tree
    me = Path(__file__).resolve()
    hits = [
        f"{f.relative_to(REPO)}:{n}: {line.strip()}"
        for f in files
        if f != me
        for n, line in enumerate(f.read_text(errors="replace").splitlines(), 1)
        if OUTSIDE.search(line)
    ]
    assert not hits, "\n".join(hits)


def test_the_pattern_catches_what_it_is_for() -> None:
    for bad in (
        'INTEROP = REPO.parent / "../shared/interop"',
        'Path("/work/shared/x.yaml")',
        "/root/.venv/bin",
    ):
        assert OUTSIDE.search(bad), bad
    assert not OUTSIDE.search('Path(__file__).parents[1] / "data" / "ethercat_driver_ros2"')
