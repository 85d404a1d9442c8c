"""Every Python block of docs/*.md and README.md runs as written, on the public API.

A page is one session: its blocks run in page order in one namespace, in a fresh empty folder.
A YAML block whose first line is a file-name comment (``# my_drive.yaml``) is a file the reader
saves: it is written under that name when the page reaches it. Comments right before a fence
(``<!-- doc-test: ... -->``, one per line) say how a block is treated:

- ``skip: REASON`` - not run (a fragment that needs the reader's own hardware or files);
- ``needs: veth`` - runs where this machine lets us make a veth pair (root, pysoem), else the
  rest of the page is skipped with the machine's reason;
- ``internal: REASON`` - documents a module below the public API (emulator internals, for
  contributors): it still runs, and may import it.

A page-wide ``<!-- doc-test: files from: PAGE.md -->`` (not right before a block) first saves the named YAML files of that page
(a page that continues another's example); ``<!-- doc-test: checkout: FOLDER -->`` first copies a
folder of the repository (e.g. ``examples/testing_your_controller``) to the same place, as a
reader with the checkout has it. Public API: ``fieldbus`` and its names,
``fieldbus.testing``, ``fieldbus.recording``; never ``sim_slaves``.
"""

from __future__ import annotations

import ast
import re
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
DOCS = REPO / "docs"
PAGES = [*sorted(DOCS.glob("*.md")), REPO / "README.md"]
PUBLIC_MODULES = ("fieldbus", "fieldbus.testing", "fieldbus.recording", "fieldbus.remote")
MARKER = re.compile(r"<!--\s*doc-test:\s*(?P<key>[a-z ]+?)\s*(?::\s*(?P<value>.*?))?\s*-->")
FILE_COMMENT = re.compile(r"#\s*([\w.-]+\.ya?ml)\s*$")


@dataclass
class Block:
    page: Path
    line: int  # of the opening fence, 1-based
    lang: str
    code: str
    markers: dict[str, str] = field(default_factory=dict)

    @property
    def where(self) -> str:
        return f"{self.page.relative_to(REPO)}:{self.line}"

    @property
    def saved_as(self) -> str | None:
        """The file name a YAML block is saved under (its first line), if any."""
        first = self.code.split("\n", 1)[0]
        m = FILE_COMMENT.fullmatch(first.strip()) if self.lang == "yaml" else None
        return m.group(1) if m else None


def blocks(page: Path) -> list[Block]:
    """The fenced blocks of ``page`` with the doc-test markers right before each."""
    lines = page.read_text().splitlines()
    out: list[Block] = []
    i = 0
    while i < len(lines):
        m = re.fullmatch(r"```(\w*)\s*", lines[i])
        if not m:
            i += 1
            continue
        start = i
        i += 1
        body: list[str] = []
        while i < len(lines) and lines[i].rstrip() != "```":
            body.append(lines[i])
            i += 1
        markers: dict[str, str] = {}
        j = start - 1
        while j >= 0 and (mk := MARKER.fullmatch(lines[j].strip())):
            markers[mk.group("key")] = mk.group("value") or ""
            j -= 1
        out.append(Block(page, start + 1, m.group(1), "\n".join(body) + "\n", markers))
        i += 1
    return out


def page_markers(page: Path) -> dict[str, str]:
    return {m.group("key"): m.group("value") or "" for m in MARKER.finditer(page.read_text())}


def _save_files(page: Path, folder: Path) -> None:
    for b in blocks(page):
        if b.saved_as:
            (folder / b.saved_as).write_text(b.code)


def _veth_refused() -> str | None:
    """Why this machine cannot make a veth pair with pysoem there, or None when it can."""
    try:
        import pysoem  # noqa: F401
    except ImportError:
        return "pysoem is not installed"
    from sim_slaves.ethercat.veth import VethUnavailable, delete_link, make_veth_pair

    try:
        master, _ = make_veth_pair()
    except VethUnavailable as exc:
        return str(exc)
    delete_link(master)
    return None


def _python_pages() -> list[Path]:
    return [p for p in PAGES if any(b.lang == "python" for b in blocks(p))]


@pytest.mark.timeout(300)
@pytest.mark.parametrize("page", _python_pages(), ids=lambda p: p.name)
def test_every_python_block_runs_as_written(
    page: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    source = page_markers(page).get("files from")
    if source:
        _save_files(DOCS / source, tmp_path)
    checkout = page_markers(page).get("checkout")
    if checkout:
        shutil.copytree(REPO / checkout, tmp_path / checkout)
    namespace: dict[str, object] = {"__name__": f"doc_{page.stem.replace('-', '_')}"}
    ran = 0
    skipped = []
    for b in blocks(page):
        if b.saved_as:
            (tmp_path / b.saved_as).write_text(b.code)
        if b.lang != "python":
            continue
        if "skip" in b.markers:
            skipped.append(f"{b.where}: {b.markers['skip']}")
            continue
        if b.markers.get("needs") == "veth" and (why := _veth_refused()) is not None:
            pytest.skip(f"{b.where} and the rest of the page need a veth pair: {why}")
        exec(compile(b.code, b.where, "exec"), namespace)
        ran += 1
    if not ran:  # every block marked not runnable, each with its reason
        pytest.skip("; ".join(skipped))


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_markers_give_a_reason(page: Path) -> None:
    for b in blocks(page):
        for key, value in b.markers.items():
            assert key in ("skip", "needs", "internal"), f"{b.where}: unknown doc-test marker {key!r}"
            assert value.strip(), f"{b.where}: doc-test marker {key!r} without a reason"
        if b.markers:
            assert b.lang == "python", f"{b.where}: doc-test markers are for Python blocks"
    for key, value in page_markers(page).items():
        if key == "files from":
            assert (DOCS / value).is_file(), f"{page.name}: files from {value}: no such page"


def _non_public(code: str) -> list[str]:
    """Imports and attribute paths of ``code`` below the public API."""
    import fieldbus

    bad = []
    for node in ast.walk(ast.parse(code)):
        modules: list[str] = []
        if isinstance(node, ast.Import):
            modules = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module:
            modules = [node.module]
        bad += [
            m for m in modules if m.split(".")[0] in ("fieldbus", "sim_slaves") and m not in PUBLIC_MODULES
        ]
        if (
            isinstance(node, ast.Attribute)
            and isinstance(node.value, ast.Name)
            and node.value.id == "fieldbus"
            and node.attr not in fieldbus.__all__
            and f"fieldbus.{node.attr}" not in PUBLIC_MODULES
        ):
            bad.append(f"fieldbus.{node.attr}")
    return bad


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_python_blocks_use_the_public_api(page: Path) -> None:
    for b in blocks(page):
        if b.lang == "python" and "internal" not in b.markers:
            assert not _non_public(b.code), f"{b.where}: below the public API: {_non_public(b.code)}"


def test_the_checks_catch_what_they_are_for() -> None:
    """The harness itself: a marker is read, a file comment names a file, internals are found."""
    page = DOCS / "tutorial.md"
    assert any(b.saved_as == "my_drive.yaml" for b in blocks(page))
    assert _non_public("from fieldbus.core.dc import DcRegister\nimport sim_slaves.od\nfieldbus.interop") == [
        "fieldbus.core.dc",
        "sim_slaves.od",
        "fieldbus.interop",
    ]
    assert _non_public("import fieldbus\nimport fieldbus.recording\nfieldbus.open_network") == []


def test_the_public_api_is_importable_from_the_top() -> None:
    import fieldbus

    for name in fieldbus.__all__:
        assert getattr(fieldbus, name) is not None, name
    for name in (
        "open_network",
        "load_drive_map",
        "ProcessImage",
        "Cia402Controller",
        "run_cycles",
        "FieldbusError",
    ):
        assert name in fieldbus.__all__, name
    assert (fieldbus.PDO_MAPS / "maxon_epos4.yaml").is_file()
    assert fieldbus.load_drive_map(fieldbus.PDO_MAPS / "maxon_epos4.yaml").vendor_id == 0xFB
