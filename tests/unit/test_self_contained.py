"""The repository stands alone: nothing it ships reads outside it or names a machine's path."""

from __future__ import annotations

import fnmatch
import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
# a path out of the checkout, or an absolute path of some machine's home, venv or work folder
OUTSIDE = re.compile(r"\.\./shared|\bshared/interop|/work/|/root/|/home/\w|/Users/\w|[A-Z]:\\\\Users")
TEXT = {".py", ".md", ".yaml", ".yml", ".toml", ".cfg", ".txt", ".c", ".sh", ""}


def _ignored(rel: Path) -> bool:
    """True for what git would not track here: .git itself and the .gitignore patterns."""
    patterns = [
        p.strip().strip("/")
        for p in (REPO / ".gitignore").read_text().splitlines()
        if p.strip() and not p.startswith("#")
    ]
    return any(part == ".git" or any(fnmatch.fnmatch(part, pat) for pat in patterns) for part in rel.parts)


def _tracked() -> list[Path]:
    """Every text file of the checkout, walked from disk (CI tests a copy without .git)."""
    files = []
    for path in REPO.rglob("*"):
        rel = path.relative_to(REPO)
        if path.suffix in TEXT and path.is_file() and not path.is_symlink() and not _ignored(rel):
            files.append(path)
    return files


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
