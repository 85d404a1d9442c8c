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
