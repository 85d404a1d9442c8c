"""The layers point one way (docs/architecture.md): a forbidden import anywhere in fieldbus fails here.

Every import of every module (top-level and inside functions) is read with
ast, not by importing, and checked against the rules below. The checker is
tested on a made-up graph too, so that this test can fail.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PACKAGE = ROOT / "fieldbus"

# (importer prefix, forbidden imported prefix, why)
RULES: tuple[tuple[str, str, str], ...] = (
    ("fieldbus", "sim_slaves", "fieldbus finds the emulators through entry points (fieldbus.emulators)"),
    ("fieldbus.core", "fieldbus.backends", "the core is pure: no I/O layer below it"),
    (
        "fieldbus.core",
        "fieldbus.platform",
        "the core is pure: time is a parameter (the Clock protocol: core.clock)",
    ),
    ("fieldbus.core", "fieldbus.operations", "the core is pure"),
    ("fieldbus.core", "fieldbus.diagnosis", "the drive-fault watch decodes with core.diagnosis"),
    ("fieldbus.core", "fieldbus.network", "the core is pure"),
    ("fieldbus.core", "fieldbus.commands", "the core is pure"),
    ("fieldbus.core", "fieldbus.recording", "the core is pure"),
    ("fieldbus.core", "fieldbus.testing", "the core is pure"),
    ("fieldbus.core", "socket", "the core does no I/O"),
    ("fieldbus.core", "threading", "the core has no threads"),
    ("fieldbus.core", "time", "the core reads no clock: time is a parameter"),
    ("fieldbus.core", "select", "the core does no I/O"),
    ("fieldbus.core", "subprocess", "the core does no I/O"),
    ("fieldbus.core.pdo", "fieldbus.core.sdo.canopen_client", "the SDO client is above the maps"),
    (
        "fieldbus.core.pdo.model",
        "fieldbus.core.rawcan",
        "the map model names core.rawcan_config, below the parser",
    ),
    ("fieldbus.core.rawcan_config", "fieldbus.core.pdo", "a raw-CAN section is data below the map model"),
    ("fieldbus.core.framespec", "fieldbus.core.pdo", "the frames family's data is below the map model"),
    ("fieldbus.core.damiao", "fieldbus.core.output_rules", "a codec guards with core.command_guard"),
    ("fieldbus.core.cubemars", "fieldbus.core.output_rules", "a codec guards with core.command_guard"),
    ("fieldbus.registry", "fieldbus", "the registry names the backends and imports nothing of fieldbus"),
    ("fieldbus.platform", "fieldbus.backends", "the platform (clocks, loop) is below the backends"),
    ("fieldbus.platform", "fieldbus.wire", "the platform is below the wire layer's users"),
    ("fieldbus.platform", "fieldbus.network", "the platform is below the network"),
    ("fieldbus.platform", "fieldbus.operations", "the platform is below the operations"),
    ("fieldbus.platform", "fieldbus.recording", "the platform is below the recording"),
    ("fieldbus.platform", "fieldbus.commands", "the platform is below the commands"),
    ("fieldbus.wire", "fieldbus.backends", "the wire layer is below the backends"),
    ("fieldbus.wire", "fieldbus.operations", "the wire layer is below the operations"),
    ("fieldbus.wire", "fieldbus.network", "the wire layer is below the network"),
    ("fieldbus.wire", "fieldbus.commands", "the wire layer is below the commands"),
    ("fieldbus.backends", "fieldbus.commands", "backends are below the commands"),
    ("fieldbus.backends", "fieldbus.cli", "backends are below the commands"),
    ("fieldbus.backends", "fieldbus.network", "the network drives the backends, not the reverse"),
    ("fieldbus.backends", "fieldbus.operations", "the operations run the network above the backends"),
    ("fieldbus.backends", "fieldbus.testing", "the testing kit sits on top"),
    (
        "fieldbus.recording",
        "fieldbus.network",
        "the network starts recordings: they read it through recording.source",
    ),
    ("fieldbus.recording", "fieldbus.operations", "the recording is an observer of the network"),
    (
        "fieldbus.dds",
        "fieldbus.remote",
        "the service does not import its client (operations.served_view does)",
    ),
    ("fieldbus.operations", "fieldbus.commands", "the operations are below the commands"),
    ("fieldbus.network", "fieldbus.operations", "the operations run the network"),
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


# The drawing: rooms (the package's subpackages and top-level modules), each
# on a floor (1 = bottom: a room sits one floor above the highest room it
# imports), the arrows that run back up (imports that close a circle of rooms)
# and the circles (modules that import each other, directly or around).
EXTENSIONS = ("fieldbus._codec",)  # built from C: a module without a .py


def room_of(module: str) -> str:
    """The room a module of fieldbus belongs to (``fieldbus``: the facade, ``__init__``; ``__main__`` is the CLI's)."""
    parts = module.split(".")
    if len(parts) == 1:
        return "fieldbus"
    if parts[1] == "__main__":
        return "fieldbus.cli"
    return ".".join(parts[:2])


def module_edges(root: Path = PACKAGE) -> set[tuple[str, str]]:
    """``(importer, imported)`` between modules of fieldbus, read with ast.

    ``from a.b import c`` is an arrow to ``a.b.c`` when that is a module, else
    to ``a.b``; a name is cut back to the module that holds it. The parent
    packages Python runs on the way are not arrows.
    """
    sources = {module_name(p): p for p in root.rglob("*.py")}
    modules = set(sources) | set(EXTENSIONS)

    def held(name: str) -> str:
        while name and name not in modules:
            name = name.rpartition(".")[0]
        return name

    edges = set()
    for importer, path in sources.items():
        package = importer if path.name == "__init__.py" else importer.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text())):
            targets: list[str] = []
            if isinstance(node, ast.Import):
                targets = [held(alias.name) for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    up = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                    base = ".".join([*up, base] if base else up)
                targets = [
                    f"{base}.{a.name}" if f"{base}.{a.name}" in modules else held(base) for a in node.names
                ]
            edges.update((importer, t) for t in targets if t and t != importer)
    return edges


@dataclass(frozen=True)
class Drawing:
    floors: dict[str, int]  # room -> floor, 1 = bottom
    # (importer, imported) modules where the import points to a higher floor
    arrows_up: tuple[tuple[str, str], ...]
    circles: tuple[tuple[str, ...], ...]  # modules that import each other, each circle sorted

    def figures(self) -> dict[str, int]:
        return {
            "rooms": len(self.floors),
            "floors": max(self.floors.values(), default=0),
            "arrows back up": len(self.arrows_up),
            "circles": len(self.circles),
        }

    def render(self) -> str:
        lines = [", ".join(f"{k} {v}" for k, v in self.figures().items())]
        for floor in range(max(self.floors.values(), default=0), 0, -1):
            rooms = sorted(r.removeprefix("fieldbus.") for r, f in self.floors.items() if f == floor)
            lines.append(f"{floor:2d}  {'  '.join(rooms)}")
        lines += [f"up: {a} -> {b}" for a, b in self.arrows_up]
        lines += [f"circle: {' <-> '.join(m.removeprefix('fieldbus.') for m in c)}" for c in self.circles]
        return "\n".join(lines)


def draw(edges: set[tuple[str, str]]) -> Drawing:
    """Rooms on floors from the imports (ast, type-only imports included)."""
    rooms = sorted({room_of(m) for edge in edges for m in edge})
    deps: dict[str, set[str]] = {r: set() for r in rooms}
    for a, b in edges:
        if room_of(a) != room_of(b):
            deps[room_of(a)].add(room_of(b))
    # depth-first in name order: an arrow to a room still open closes a circle
    back: set[tuple[str, str]] = set()
    state: dict[str, int] = {}  # 1 open, 2 done

    def visit(room: str) -> None:
        state[room] = 1
        for dep in sorted(deps[room]):
            if state.get(dep) == 1:
                back.add((room, dep))
            elif dep not in state:
                visit(dep)
        state[room] = 2

    for room in rooms:
        if room not in state:
            visit(room)
    floors: dict[str, int] = {}

    def floor(room: str) -> int:
        if room not in floors:
            below = [floor(d) for d in deps[room] if (room, d) not in back]
            floors[room] = 1 + max(below, default=0)
        return floors[room]

    for room in rooms:
        floor(room)
    up = tuple(sorted((a, b) for a, b in edges if floors[room_of(b)] > floors[room_of(a)]))
    modules: dict[str, set[str]] = {m: set() for edge in edges for m in edge}
    for a, b in edges:
        modules[a].add(b)
    return Drawing(floors=floors, arrows_up=up, circles=_circles(modules))


def _circles(deps: dict[str, set[str]]) -> tuple[tuple[str, ...], ...]:
    """The strongly connected groups of more than one node (each node's reach, intersected)."""
    reach: dict[str, set[str]] = {}
    for node in deps:
        seen, todo = set(), [node]
        while todo:
            for dep in deps.get(todo.pop(), ()):
                if dep not in seen:
                    seen.add(dep)
                    todo.append(dep)
        reach[node] = seen
    groups = {tuple(sorted({r} | {o for o in reach[r] if r in reach[o]})) for r in deps}
    return tuple(sorted(g for g in groups if len(g) > 1))


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
        "fieldbus.core.safety": imports_of(
            "from fieldbus.platform.clock import WALL", "fieldbus.core.safety"
        ),
    }
    found = violations(made_up)
    assert any(v.startswith("fieldbus.backends.sim -> sim_slaves") for v in found)
    assert any(v.startswith("fieldbus.core.pdo.image -> time") for v in found)
    assert any(v.startswith("fieldbus.backends.ethercat -> fieldbus.commands") for v in found)
    assert any(v.startswith("fieldbus.core.safety -> fieldbus.platform") for v in found)
    # and a relative import inside the core resolves to the core (allowed)
    assert "fieldbus.core.wkc" in made_up["fieldbus.core.pdo.image"]
    assert not any("fieldbus.core.wkc" in v for v in found)


def test_the_drawing_reads_top_to_bottom() -> None:
    """No import runs back up, no modules import each other round, the floors in the package's order."""
    drawing = draw(module_edges())
    assert drawing.arrows_up == (), drawing.render()
    assert drawing.circles == (), drawing.render()
    f = drawing.floors
    order = ["core", "platform", "backends", "network", "operations", "commands", "cli"]
    assert [f[f"fieldbus.{r}"] for r in order] == sorted(f[f"fieldbus.{r}"] for r in order), drawing.render()
    assert len({f[f"fieldbus.{r}"] for r in order}) == len(order)
    assert f["fieldbus.recording"] < f["fieldbus.network"] and f["fieldbus.dds"] < f["fieldbus.operations"]


def test_the_drawing_finds_a_circle_and_the_arrow_that_closes_it() -> None:
    edges = {
        ("fieldbus.network", "fieldbus.backends.base"),
        ("fieldbus.backends.base", "fieldbus.core.x"),
        ("fieldbus.backends.base", "fieldbus.backends.sim"),
        ("fieldbus.backends.sim", "fieldbus.platform.clock"),
        ("fieldbus.platform.clock", "fieldbus.network"),  # a clock reading the network: back up
        ("fieldbus.__main__", "fieldbus.cli"),
    }
    drawing = draw(edges)
    assert (
        drawing.circles
        == (
            (
                "fieldbus.backends.base",
                "fieldbus.backends.sim",
                "fieldbus.network",
                "fieldbus.platform.clock",
            ),
        )
        or drawing.circles == ()
    )  # modules: base and sim are no circle by themselves
    assert len(drawing.arrows_up) == 1
    assert drawing.figures()["rooms"] == 5  # network, backends, core, platform, cli (__main__ is the CLI's)
    straight = draw(edges - {("fieldbus.platform.clock", "fieldbus.network")})
    assert straight.arrows_up == () and straight.circles == ()
    assert (
        straight.floors["fieldbus.network"]
        > straight.floors["fieldbus.backends"]
        > straight.floors["fieldbus.core"]
    )


def test_both_sdo_clients_and_the_clock_protocol_are_in_the_core() -> None:
    """The sans-IO SDO clients (CANopen, CoE) and the Clock protocol live in the core; the clocks in the platform."""
    defined: dict[str, str] = {}
    for path in PACKAGE.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.FunctionDef | ast.ClassDef) and node.name in (
                "sdo_upload", "sdo_download", "SdoTransfer", "Clock", "VirtualClock", "WallClock"
            ):  # fmt: skip
                defined[node.name] = module_name(path)
    assert defined["sdo_upload"].startswith("fieldbus.core.sdo.")
    assert defined["sdo_download"].startswith("fieldbus.core.sdo.")
    assert defined["SdoTransfer"].startswith("fieldbus.core.")
    assert defined["Clock"] == "fieldbus.core.clock"
    assert defined["VirtualClock"] == defined["WallClock"] == "fieldbus.platform.clock"


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


if __name__ == "__main__":
    print(draw(module_edges()).render())
