"""The Python blocks of docs/tutorial.md run as written."""

from __future__ import annotations

import re
from pathlib import Path

DOCS = Path(__file__).resolve().parents[2] / "docs"


def test_tutorial_python_blocks_run() -> None:
    text = (DOCS / "tutorial.md").read_text()
    yaml_block = re.search(r"```yaml\n(# my_drive.yaml\n.*?)```", text, re.S)
    assert yaml_block is not None
    namespace: dict[str, object] = {"MY_DRIVE": yaml_block.group(1)}
    blocks = re.findall(r"```python\n(.*?)```", text, re.S)
    assert len(blocks) >= 3
    for block in blocks:
        exec(compile(block, "docs/tutorial.md", "exec"), namespace)


def test_tutorial_uses_the_public_names_only() -> None:
    blocks = re.findall(r"```python\n(.*?)```", (DOCS / "tutorial.md").read_text(), re.S)
    inner = [
        line for b in blocks for line in b.splitlines() if re.match(r"\s*(from|import) fieldbus\.", line)
    ]
    assert not inner, inner


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
