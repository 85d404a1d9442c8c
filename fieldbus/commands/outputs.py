"""Output paths checked before a command runs: a plot, a map, a log or a folder it will write.

Each check raises :class:`OutputError` (exit 1) naming the flag and the path, so that a bad
``--plot`` or ``-o`` is refused at once instead of after the whole run. Nothing is left behind:
a file that did not exist is created and removed again, a folder is only probed.
"""

from __future__ import annotations

import errno
import os
import stat
import tempfile
from pathlib import Path

from fieldbus.errors import BackendUnavailableError, FieldbusError


class OutputError(FieldbusError):
    """A command's output path cannot be written (a missing folder, a directory, /proc, no permission)."""


def _why(exc: OSError, creating: bool) -> str:
    if creating and exc.errno == errno.ENOENT:
        return "this folder does not take new files"  # /proc, /sys
    return exc.strerror or type(exc).__name__


def check_file(path: str | os.PathLike[str] | None, flag: str) -> None:
    """``path`` can be written as a file (its folder exists and takes it); nothing is changed."""
    if not path:
        return
    p = Path(path)
    where = f"{flag} {os.fspath(path)}"
    if p.is_dir():
        raise OutputError(f"{where}: is a folder; give a file name in it")
    folder = p.parent
    if not folder.exists():
        raise OutputError(f"{where}: the folder {folder} does not exist")
    if not folder.is_dir():
        raise OutputError(f"{where}: {folder} is not a folder")
    if p.exists():
        mode = p.stat().st_mode
        if stat.S_ISREG(mode):
            try:
                with open(p, "ab"):  # append mode: the content and its time stay as they are
                    pass
            except OSError as exc:
                raise OutputError(f"{where}: cannot write it: {_why(exc, False)}") from None
        elif not os.access(p, os.W_OK):
            raise OutputError(f"{where}: cannot write it")
        return
    try:
        fd = os.open(p, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
    except OSError as exc:
        raise OutputError(f"{where}: cannot create it: {_why(exc, True)}") from None
    os.close(fd)
    os.unlink(p)


def check_folder(path: str | os.PathLike[str] | None, flag: str) -> None:
    """``path`` is a folder that takes new files, or one that can be made (with its parents)."""
    if not path:
        return
    p = Path(path)
    where = f"{flag} {os.fspath(path)}"
    if p.exists() and not p.is_dir():
        raise OutputError(f"{where}: exists and is not a folder")
    probe_in = p
    while not probe_in.exists():
        if probe_in.parent == probe_in:
            break
        probe_in = probe_in.parent
    if not probe_in.is_dir():
        raise OutputError(f"{where}: {probe_in} is not a folder")
    try:
        if probe_in == p:
            fd, name = tempfile.mkstemp(dir=p, prefix=".fieldbus-probe-")
            os.close(fd)
            os.unlink(name)
        else:
            os.rmdir(tempfile.mkdtemp(dir=probe_in, prefix=".fieldbus-probe-"))
    except OSError as exc:
        raise OutputError(f"{where}: cannot write in {probe_in}: {_why(exc, True)}") from None


def check_plot(path: str | os.PathLike[str] | None, flag: str) -> None:
    """:func:`check_file`, and matplotlib is installed and writes the format the suffix names.

    Without a suffix matplotlib writes ``path.png``: that file is checked (a folder is refused)."""
    if not path:
        return
    p = Path(path)
    if p.is_dir():
        raise OutputError(f"{flag} {os.fspath(path)}: is a folder; give a file name in it")
    check_file(p if p.suffix else p.with_name(p.name + ".png"), flag)
    try:
        from matplotlib.backend_bases import FigureCanvasBase
    except ImportError:
        raise BackendUnavailableError(f"{flag} needs matplotlib: pip install 'fieldbus[plot]'") from None
    suffix = Path(path).suffix.lower().lstrip(".")
    formats = FigureCanvasBase.get_supported_filetypes()
    if suffix and suffix not in formats:
        known = ", ".join(f".{k}" for k in sorted(formats))
        raise OutputError(f"{flag} {os.fspath(path)}: matplotlib cannot write .{suffix} files ({known})")
