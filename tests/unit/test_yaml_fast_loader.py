"""libyaml reads the maps when installed (several times faster: the suite loads thousands); it must give
the same data and the same positions as PyYAML's own reader, and its refusals PyYAML's errors."""

from __future__ import annotations

from pathlib import Path

import pytest

import fieldbus
from fieldbus.core import yamlsrc
from fieldbus.errors import PdoMapError

REPO = Path(__file__).resolve().parents[2]
FILES = [
    *sorted(fieldbus.PDO_MAPS.glob("*.yaml")),
    *sorted((REPO / "examples").rglob("*.yaml")),
    *sorted((REPO / "tests" / "data").glob("*.yaml")),
]


def _both(text: str, monkeypatch: pytest.MonkeyPatch) -> tuple[object, object]:
    def read() -> object:
        try:
            d = yamlsrc.load_located(text, "f.yaml")
        except PdoMapError as exc:
            return ("error", str(exc), exc.line, exc.column)
        return (d.data, dict(d.values), dict(d.keys))

    fast = read()
    with monkeypatch.context() as m:
        m.setattr(yamlsrc, "_FastLoader", None)
        slow = read()
    return fast, slow


@pytest.mark.skipif(yamlsrc._FastLoader is None, reason="PyYAML without libyaml: one reader only")
@pytest.mark.parametrize("path", FILES, ids=lambda p: p.name)
def test_libyaml_gives_the_same_data_and_positions(path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    fast, slow = _both(path.read_text(), monkeypatch)
    assert fast == slow


@pytest.mark.skipif(yamlsrc._FastLoader is None, reason="PyYAML without libyaml: one reader only")
@pytest.mark.parametrize(
    "text",
    [
        "a: [1, 2\n",
        "a: 1\n b: 2\n",
        "x: \x07\n",
        "- &a [*a]\n",
        "a: !!python/object:os.system x\n",
        "k: 5e-6\n",
    ],
)
def test_what_libyaml_refuses_is_pyyamls_error(text: str, monkeypatch: pytest.MonkeyPatch) -> None:
    fast, slow = _both(text, monkeypatch)
    assert fast == slow
