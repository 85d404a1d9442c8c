"""Functions stay short enough to read top to bottom: over 80 lines only those not split yet.

Every function and method of fieldbus/ and sim_slaves/ (nested ones too) is measured with ast, from
its ``def`` to its last line. The allow-list names the long ones still to split, each with the length
it had when listed: a new long function fails, one that grew fails, and one split (or shortened
under the limit) must leave the list, so the count only goes down.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
LIMIT = 80  # lines, def to last line

# "file.py::qualified.name" (the file's name, not its folder: a module moved to another package keeps
# its entry): its length when listed (not yet split into pieces with names in the domain)
ALLOWED: dict[str, int] = {}


def function_lengths(source: str, path: str) -> dict[str, int]:
    """``path::Class.method`` (nested functions as ``outer.inner``) -> lines from ``def`` to its end."""
    out: dict[str, int] = {}

    def walk(node: ast.AST, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef):
                name = f"{prefix}{child.name}"
                out[f"{path}::{name}"] = (child.end_lineno or child.lineno) - child.lineno + 1
                walk(child, f"{name}.")
            elif isinstance(child, ast.ClassDef):
                walk(child, f"{prefix}{child.name}.")
            else:
                walk(child, prefix)

    walk(ast.parse(source), "")
    return out


def all_functions() -> dict[str, int]:
    """Every function of fieldbus/ and sim_slaves/ -> its length (two files of one name: the longer counts)."""
    found: dict[str, int] = {}
    for package in ("fieldbus", "sim_slaves"):
        for p in sorted((ROOT / package).rglob("*.py")):
            for key, n in function_lengths(p.read_text(), p.name).items():
                found[key] = max(n, found.get(key, 0))
    return found


def long_functions() -> dict[str, int]:
    return {k: n for k, n in all_functions().items() if n > LIMIT}


def test_no_function_is_longer_than_80_lines_but_those_not_split_yet() -> None:
    assert len(all_functions()) > 1000  # the packages were read
    found = long_functions()
    new = {k: n for k, n in found.items() if k not in ALLOWED}
    assert not new, f"over {LIMIT} lines: split them into pieces named in the domain: {new}"
    grown = {k: (ALLOWED[k], n) for k, n in found.items() if n > ALLOWED[k]}
    assert not grown, f"longer than when they were listed (listed, now): {grown}"
    gone = sorted(set(ALLOWED) - set(found))
    assert not gone, f"no longer over {LIMIT} lines (or renamed): take them off ALLOWED: {gone}"


def test_the_measure_counts_methods_and_nested_functions() -> None:
    body = "\n".join(f"        x{i} = {i}" for i in range(LIMIT))
    source = f"class A:\n    def long(self):\n{body}\n        def inner():\n            pass\n\ndef short():\n    pass\n"
    got = function_lengths(source, "m.py")
    assert got == {"m.py::A.long": LIMIT + 3, "m.py::A.long.inner": 2, "m.py::short": 2}
