"""What a new user copies from the docs works as written: files the commands name exist, and calls
read as what they mean (a cycle time is passed by keyword, not mistaken for a rate)."""

from __future__ import annotations

import re
from pathlib import Path

import fieldbus

REPO = Path(__file__).resolve().parents[2]
PAGES = [*sorted((REPO / "docs").glob("*.md")), REPO / "README.md"]


def test_the_dds_page_serves_a_network_file_of_the_repository() -> None:
    text = (REPO / "docs" / "dds.md").read_text()
    served = re.findall(r"^fieldbus serve (\S+\.ya?ml)", text, re.M)
    assert served, "no 'fieldbus serve FILE' command on the page"
    for name in served:
        path = REPO / name
        assert path.is_file(), f"docs/dds.md serves {name}, which is not in the repository"
        assert fieldbus.load_network(path).buses  # a network file, loadable as it is


def test_run_cycles_in_the_docs_takes_the_cycle_time_by_keyword() -> None:
    # run_cycles(step, 1000.0, 600): 1000.0 reads as a rate in Hz, it is a cycle time in us
    positional = re.compile(r"run_cycles\(\s*[\w.]+\s*,\s*[\d.]+")
    found = [f"{p.name}: {m.group(0)}" for p in PAGES for m in positional.finditer(p.read_text())]
    assert not found, found
    tutorial = (REPO / "docs" / "tutorial.md").read_text()
    assert "run_cycles(cycle, cycle_time_us=1000.0, cycles=5000)" in tutorial
