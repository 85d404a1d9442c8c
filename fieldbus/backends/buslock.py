"""One master per interface: an exclusive lock per network card (EtherCAT) and per CAN channel.

A lock is a file ``<dir>/<name>.lock`` held with ``flock(2)`` (exclusive, never
waiting) and holding the owner's PID and program name; ``<dir>`` is
``/run/lock/fieldbus``, or ``fieldbus-lock`` in the temporary directory where
that cannot be written. The kernel drops the lock when its process dies, so a
crashed master never blocks the next one; a clean release removes the file.
A second master is refused at ``open()`` with :class:`InterfaceInUseError`
("interface 'eth0' is in use by PID 1234 (fieldbus)").

python-can's ``virtual`` channels exist inside one process only (another
process with the same channel name is on another bus): they are locked in a
table of this process instead of a file.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import hashlib
import os
import re
import sys
import tempfile
import threading
import weakref
from collections.abc import Iterable
from pathlib import Path

from fieldbus.core.network import Bus
from fieldbus.errors import FieldbusError, InterfaceInUseError

LOCK_DIR = Path("/run/lock/fieldbus")
FALLBACK_DIR_NAME = "fieldbus-lock"  # under tempfile.gettempdir()
IN_PROCESS_INTERFACES = ("virtual",)  # python-can interfaces whose channels live in one process
DEFAULT_UDP_PORT = 43113  # python-can's udp_multicast and fieldbus_udp: the port when none is given
_SAFE = re.compile(r"[^A-Za-z0-9._-]")
_ATTEMPTS = 5  # a lock file removed between our open and flock is opened again, this many times

_local_lock = threading.Lock()
_local_owners: set[str] = set()  # keys of in-process locks held now


def _program() -> str:
    """This process's program: the script's name (``fieldbus``), else the interpreter's."""
    script = Path(sys.argv[0]) if sys.argv and sys.argv[0] not in ("", "-c", "-m") else None
    if script is not None:
        return script.parent.name if script.name == "__main__.py" else script.name  # python -m pkg: pkg
    return Path(sys.executable).name or "python"


def lock_dir() -> Path:
    """Where lock files go: ``/run/lock/fieldbus`` when it can be used, else a folder in the temp dir."""
    for d in (LOCK_DIR, Path(tempfile.gettempdir()) / FALLBACK_DIR_NAME):
        try:
            if not d.is_dir():
                d.mkdir(parents=False)
                d.chmod(0o1777)  # every user's masters lock here (sticky: each removes only its own)
            if os.access(d, os.W_OK | os.X_OK):
                return d
        except OSError:
            continue
    raise FieldbusError(f"no folder for interface locks: neither {LOCK_DIR} nor the temp dir is writable")


def file_name(key: str) -> str:
    """A file name for ``key``: its safe characters, plus a short hash when some had to be replaced."""
    safe = _SAFE.sub("_", key)
    if safe != key:
        safe += "-" + hashlib.sha1(key.encode()).hexdigest()[:8]
    return safe + ".lock"


class InterfaceLock:
    """An exclusive lock on one interface, held until :meth:`release` (idempotent) or process exit."""

    def __init__(self, label: str, key: str, *, in_process: bool = False) -> None:
        """Take the lock; raises :class:`InterfaceInUseError` when another master holds it.

        ``label`` names the interface in messages, ``key`` identifies it (the lock file's name).
        """
        self.label = label
        self.key = key
        self.path: Path | None = None
        self._fd = -1
        self._finalizer: weakref.finalize[..., InterfaceLock]
        if in_process:
            with _local_lock:
                if key in _local_owners:
                    raise InterfaceInUseError(label, os.getpid(), f"{_program()}, this process")
                _local_owners.add(key)
            self._finalizer = weakref.finalize(self, _release_local, key)
            return
        path = lock_dir() / file_name(key)
        fd = _acquire_file(path, label)
        self.path, self._fd = path, fd
        self._finalizer = weakref.finalize(self, _release_file, path, fd)

    @property
    def held(self) -> bool:
        return self._finalizer.alive

    def release(self) -> None:
        """Give the interface up (removes the lock file). Never raises."""
        self._finalizer()

    def __enter__(self) -> InterfaceLock:
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


def _acquire_file(path: Path, label: str) -> int:
    for _ in range(_ATTEMPTS):
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        except PermissionError:  # another user's lock file: read-only still takes part in flock
            fd = os.open(path, os.O_RDONLY | os.O_CLOEXEC)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            pid, program = _holder(fd)
            os.close(fd)
            if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise InterfaceInUseError(label, pid, program) from None
            raise FieldbusError(f"cannot lock interface '{label}' ({path}): {exc}") from exc
        try:  # the file we locked may have been removed by its last owner meanwhile: then lock the new one
            same = os.fstat(fd).st_ino == os.stat(path).st_ino
        except FileNotFoundError:
            same = False
        if not same:
            os.close(fd)
            continue
        with contextlib.suppress(OSError):  # a read-only lock file keeps the old text
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n{_program()}\n".encode(), 0)
        return fd
    raise FieldbusError(f"cannot lock interface '{label}' ({path}): its lock file keeps being replaced")


def _holder(fd: int) -> tuple[int | None, str]:
    """The PID and program written in a lock file (None, "" when unreadable)."""
    try:
        text = os.pread(fd, 256, 0).decode(errors="replace").split("\n")
        return int(text[0]), text[1].strip() if len(text) > 1 else ""
    except (OSError, ValueError):
        return None, ""


def _release_file(path: Path, fd: int) -> None:
    with contextlib.suppress(OSError):
        if os.fstat(fd).st_ino == os.stat(path).st_ino:
            path.unlink()  # still holding it: nobody can have locked this file meanwhile
    with contextlib.suppress(OSError):
        os.close(fd)  # releases the flock


def _release_local(key: str) -> None:
    with _local_lock:
        _local_owners.discard(key)


def lock_network_card(name: str) -> InterfaceLock:
    """The lock of network card ``name`` (EtherCAT: the NIC the master sends its frames on)."""
    return InterfaceLock(name, f"net.{name}")


def lock_can_bus(bus: Bus) -> InterfaceLock:
    """The lock of a CAN bus's python-can channel: interface type, channel and, for UDP ones, port."""
    interface = bus.can_interface or "socketcan"
    channel = bus.interface if bus.interface is not None else "default"
    options = dict(bus.can_options)
    where = str(channel)
    if interface.startswith("udp_multicast") or interface == "fieldbus_udp":
        where = f"{channel}:{options.get('port', DEFAULT_UDP_PORT)}"
    label = where if interface == "socketcan" else f"{interface} {where}"
    return InterfaceLock(label, f"can.{interface}.{where}", in_process=interface in IN_PROCESS_INTERFACES)


def release_all(locks: Iterable[InterfaceLock]) -> None:
    for lock in locks:
        lock.release()
