"""One entry point for "a device described in a file": drive map, ESI or EDS/DCF, by suffix.

Used where a drive is named by a file and the user may hold a vendor description
rather than a drive map: the emulators (``python -m sim_slaves.ethercat --map
servo.xml``), tests and tools. ESI files with several devices take the choice
after a ``#``: ``easycat.xml#EasyCAT 64+64 rev 1`` or ``easycat.xml#0x00DEFEDE:0x5A01``.
"""

from __future__ import annotations

from pathlib import Path

from fieldbus.core.pdo.load import load_drive_map
from fieldbus.core.pdo.model import DriveMap

ESI_SUFFIXES = (".xml",)
EDS_SUFFIXES = (".eds", ".dcf")


def load_device(spec: str | Path) -> DriveMap:
    """The drive map of ``spec``: a drive map YAML, an ESI XML (``FILE.xml[#DEVICE]``) or an EDS/DCF."""
    text = str(spec)
    path, _, device = text.partition("#") if ".xml#" in text.lower() else (text, "", "")
    suffix = Path(path).suffix.lower()
    if suffix in ESI_SUFFIXES:
        from fieldbus.interop.esi import import_esi_file

        return import_esi_file(path, device=device or None).drive
    if suffix in EDS_SUFFIXES:
        from fieldbus.interop.eds import import_eds

        return import_eds(path).drive
    return load_drive_map(path)
