"""A network file's ``emulator:`` section is opaque to fieldbus: kept as written, validated by the emulator.

With ``sim_slaves`` installed its validator (the emulator part ``emulator_options``)
refuses a bad option at load time, located as every other error of the file,
also through ``fieldbus validate``; without it (blocked in a subprocess, as
tests/unit/test_layers.py does) fieldbus loads the file and keeps the section.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from fieldbus.cli import main
from fieldbus.core.emulator_opts import EmulatorSection
from fieldbus.core.network import network_from_text
from fieldbus.errors import PdoMapError

ROOT = Path(__file__).resolve().parents[2]
DEMO_MAP = ROOT / "fieldbus" / "data" / "demo_joint.yaml"
NET = """cycle_time_us: 500
buses:
  - name: arm
    type: ethercat
    interface: sim
    slaves:
      - name: j0
        map: {map}
        emulator:
          command_delay_us: 1500
          {extra}
"""
BLOCK_SIM_SLAVES = """
import sys
class _Block:
    def find_spec(self, name, path=None, target=None):
        if name == "sim_slaves" or name.startswith("sim_slaves."):
            raise ImportError(f"{name} is not installed (blocked by the test)", name=name)
        return None
sys.meta_path.insert(0, _Block())
"""


def test_the_section_is_kept_as_written_with_its_place_in_the_file() -> None:
    net = network_from_text(NET.format(map=DEMO_MAP, extra="thermal: true"), "net.yaml")
    section = net.buses[0].slaves[0].emulator
    assert isinstance(section, EmulatorSection)
    assert dict(section.options) == {"command_delay_us": 1500, "thermal": True}
    assert section.cycle_time_us == 500
    assert section.path == ("buses", 0, "slaves", 0, "emulator")
    where = section.doc.where((*section.path, "thermal"))
    assert where[0] == 11  # line of `thermal: true` in NET


def test_fieldbus_validate_names_file_line_and_key_of_a_bad_emulator_option(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "net.yaml"
    path.write_text(NET.format(map=DEMO_MAP, extra="coulomb_friction_nm: -0.5"))
    assert main(["validate", str(path)]) == 1
    err = capsys.readouterr().err
    assert "net.yaml:11:" in err, err
    assert "coulomb_friction_nm" in err and "must be >= 0" in err, err


def test_without_the_emulators_the_section_is_accepted_and_ignored(tmp_path: Path) -> None:
    path = tmp_path / "net.yaml"
    path.write_text(NET.format(map=DEMO_MAP, extra="no_such_option: [1, 2]"))
    code = BLOCK_SIM_SLAVES + (
        "from fieldbus.core.network import load_network\n"
        "from fieldbus.cli import main\n"
        f"section = load_network({str(path)!r}).buses[0].slaves[0].emulator\n"
        "print(sorted(section.options))\n"
        f"assert main(['validate', {str(path)!r}]) == 0\n"
        "assert 'sim_slaves' not in sys.modules\n"
        "print('ok')\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    assert lines[0] == "['command_delay_us', 'no_such_option']" and lines[-1] == "ok", out.stdout
    # the same file with the emulators installed: the unknown key is refused, located
    with pytest.raises(PdoMapError, match="no_such_option") as info:
        network_from_text(path.read_text(), str(path))
    assert f"{path}:11:" in str(info.value)
