"""The layers point one way (docs/architecture.md): a forbidden import anywhere in fieldbus fails here.

Every import of every module (top-level and inside functions) is read with
ast, not by importing, and checked against the rules below. The checker is
tested on a made-up graph too, so that this test can fail.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PACKAGE = ROOT / "fieldbus"

# (importer prefix, forbidden imported prefix, why)
RULES: tuple[tuple[str, str, str], ...] = (
    ("fieldbus", "sim_slaves", "fieldbus finds the emulators through entry points (fieldbus.emulators)"),
    ("fieldbus.core", "fieldbus.backends", "the core is pure: no I/O layer below it"),
    ("fieldbus.core", "fieldbus.runtime", "the core is pure: time is a parameter"),
    ("fieldbus.core", "fieldbus.network", "the core is pure"),
    ("fieldbus.core", "fieldbus.commands", "the core is pure"),
    ("fieldbus.core", "fieldbus.recording", "the core is pure"),
    ("fieldbus.core", "fieldbus.testing", "the core is pure"),
    ("fieldbus.core", "socket", "the core does no I/O"),
    ("fieldbus.core", "threading", "the core has no threads"),
    ("fieldbus.core", "time", "the core reads no clock: time is a parameter"),
    ("fieldbus.core", "select", "the core does no I/O"),
    ("fieldbus.core", "subprocess", "the core does no I/O"),
    ("fieldbus.wire", "fieldbus.backends", "the wire layer is below the backends"),
    ("fieldbus.wire", "fieldbus.runtime", "the wire layer is below the runtime"),
    ("fieldbus.wire", "fieldbus.network", "the wire layer is below the network"),
    ("fieldbus.wire", "fieldbus.commands", "the wire layer is below the commands"),
    ("fieldbus.backends", "fieldbus.commands", "backends are below the commands"),
    ("fieldbus.backends", "fieldbus.cli", "backends are below the commands"),
    ("fieldbus.backends", "fieldbus.network", "the network drives the backends, not the reverse"),
    ("fieldbus.backends", "fieldbus.testing", "the testing kit sits on top"),
    ("fieldbus.runtime", "fieldbus.commands", "the runtime is below the commands"),
    ("fieldbus.network", "fieldbus.commands", "the API is below the commands"),
    ("fieldbus.core", "fieldbus.cycle", "the core is pure"),
    ("fieldbus.backends", "fieldbus.cycle", "the cycle's parts drive the backends, not the reverse"),
    ("fieldbus.cycle", "fieldbus.network", "the parts are below their facade, Operational"),
    ("fieldbus.cycle", "fieldbus.recording", "a recording is an observer of the cycle's events"),
    ("fieldbus.cycle", "fieldbus.commands", "the cycle is below the commands"),
    ("fieldbus.cycle", "fieldbus.testing", "the testing kit sits on top"),
    ("fieldbus.network", "fieldbus.testing", "the testing kit sits on top"),
)


def module_name(path: Path) -> str:
    rel = path.relative_to(ROOT).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def imports_of(source: str, module: str, is_package: bool = False) -> set[str]:
    """Every module ``module`` imports (absolute names; relative imports resolved)."""
    found: set[str] = set()
    package = module if is_package else module.rpartition(".")[0]
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.split(".")
                up = up[: len(up) - (node.level - 1)]
                base = ".".join([*up, base] if base else up)
            found.add(base)
            found.update(f"{base}.{alias.name}" for alias in node.names)
    return found


def _under(name: str, prefix: str) -> bool:
    return name == prefix or name.startswith(prefix + ".")


def violations(graph: dict[str, set[str]]) -> list[str]:
    """``importer -> imported: why`` for every import that breaks a rule."""
    out = []
    for importer, imported in sorted(graph.items()):
        for target in sorted(imported):
            for src, dst, why in RULES:
                if _under(importer, src) and _under(target, dst):
                    out.append(f"{importer} -> {target}: {why}")
    return out


def package_graph() -> dict[str, set[str]]:
    graph = {}
    for path in PACKAGE.rglob("*.py"):
        name = module_name(path)
        graph[name] = imports_of(path.read_text(), name, path.name == "__init__.py")
    return graph


def test_no_module_of_fieldbus_breaks_a_layer_rule() -> None:
    graph = package_graph()
    assert len(graph) > 80  # the whole package was read
    assert violations(graph) == []


def test_the_checker_catches_each_kind_of_forbidden_arrow() -> None:
    made_up = {
        "fieldbus.backends.sim": imports_of(
            "from sim_slaves.ethercat.chain import EscChain", "fieldbus.backends.sim"
        ),
        "fieldbus.core.pdo.image": imports_of("import time\nfrom ..wkc import x", "fieldbus.core.pdo.image"),
        "fieldbus.backends.ethercat": imports_of(
            "def f():\n    from fieldbus.commands.demo import DEMO_MAP", "fieldbus.backends.ethercat"
        ),
        "fieldbus.core.safety": imports_of("from fieldbus.runtime.clock import WALL", "fieldbus.core.safety"),
    }
    found = violations(made_up)
    assert any(v.startswith("fieldbus.backends.sim -> sim_slaves") for v in found)
    assert any(v.startswith("fieldbus.core.pdo.image -> time") for v in found)
    assert any(v.startswith("fieldbus.backends.ethercat -> fieldbus.commands") for v in found)
    assert any(v.startswith("fieldbus.core.safety -> fieldbus.runtime") for v in found)
    # and a relative import inside the core resolves to the core (allowed)
    assert "fieldbus.core.wkc" in made_up["fieldbus.core.pdo.image"]
    assert not any("fieldbus.core.wkc" in v for v in found)


BLOCK_SIM_SLAVES = """
import sys
class _Block:
    def find_spec(self, name, path=None, target=None):
        if name == "sim_slaves" or name.startswith("sim_slaves."):
            raise ImportError(f"{name} is not installed (blocked by the test)", name=name)
        return None
sys.meta_path.insert(0, _Block())
"""


def test_fieldbus_imports_and_builds_a_network_without_sim_slaves() -> None:
    code = BLOCK_SIM_SLAVES + (
        "import fieldbus, fieldbus.network, fieldbus.backends.ethercat, fieldbus.backends.canopen\n"
        "import fieldbus.backends.rawcan, fieldbus.backends.sim, fieldbus.testing, fieldbus.cli\n"
        "from fieldbus.emulators import EmulatorsUnavailable, emulator_part\n"
        "try:\n"
        "    emulator_part('ethercat_chain')\n"
        "except EmulatorsUnavailable as exc:\n"
        "    print('refused:', exc)\n"
        "assert 'sim_slaves' not in sys.modules\n"
        "print('ok')\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.splitlines()[-1] == "ok"
    assert "refused: the emulator part 'ethercat_chain' needs the Python package 'sim_slaves" in out.stdout
