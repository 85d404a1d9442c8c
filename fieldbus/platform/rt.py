"""Real-time settings for the thread that runs the cycle: SCHED_FIFO, CPU affinity, locked memory.

What every real-time Linux master relies on (SOEM on PREEMPT_RT, IgH,
ros2_control): the cycle thread at a fixed real-time priority, pinned to a CPU,
its memory locked so that no page fault stalls a cycle. :func:`realtime`
applies what :class:`RtConfig` asks for and restores the previous settings on
exit. A setting the system refuses gives one line naming the capability or
limit it needs (or, with ``strict``, an :class:`RtError`); the others still
apply.

Scheduling and affinity apply to the calling thread (Linux: ``pid 0``);
``mlockall`` to the whole process. Prefaulting touches ``prefault_heap_mb`` of
heap once, so the allocator's pages are mapped and locked before the cycle
needs them (Python 3.11 keeps its frames on the heap; the thread's C stack is
locked as it stands by ``MCL_CURRENT`` and as it grows by ``MCL_FUTURE``).
"""

from __future__ import annotations

import ctypes
import errno
import os
import resource
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field

from fieldbus.errors import FieldbusError

MCL_CURRENT, MCL_FUTURE = 1, 2
PAGE = 4096


class RtError(FieldbusError):
    """A real-time setting was refused and ``strict`` asked for it to be an error."""


@dataclass(frozen=True)
class RtConfig:
    """``priority``: SCHED_FIFO 1-99 (None: leave the policy); ``cpu``: pin to it (None: leave);
    ``lock_memory``: mlockall + prefault; ``strict``: a refusal raises :class:`RtError`."""

    priority: int | None = None
    cpu: int | None = None
    lock_memory: bool = False
    strict: bool = False
    prefault_heap_mb: int = 16

    @property
    def requested(self) -> bool:
        return self.priority is not None or self.cpu is not None or self.lock_memory


@dataclass
class RtState:
    """What :func:`realtime` applied and what it could not."""

    applied: list[str] = field(default_factory=list)
    refused: list[str] = field(default_factory=list)

    def to_json(self) -> dict[str, list[str]]:
        return {"applied": self.applied, "refused": self.refused}


def _libc() -> ctypes.CDLL:
    return ctypes.CDLL(None, use_errno=True)


def _limit(res: int) -> str:
    soft, _hard = resource.getrlimit(res)
    return "unlimited" if soft == resource.RLIM_INFINITY else str(soft)


def _prefault(cfg: RtConfig) -> None:
    heap = bytearray(cfg.prefault_heap_mb << 20)
    for i in range(0, len(heap), PAGE):  # touch every page once; freed, they stay mapped for the allocator
        heap[i] = 1
    del heap


@contextmanager
def realtime(cfg: RtConfig, warn: Callable[[str], None] | None = None) -> Iterator[RtState]:
    """Apply ``cfg`` to the calling thread (and lock the process's memory); restore everything on exit."""
    state = RtState()

    def refuse(msg: str) -> None:
        if cfg.strict:
            raise RtError(msg)
        state.refused.append(msg)
        if warn is not None:
            warn(f"real-time: {msg}")

    old_policy = os.sched_getscheduler(0)
    old_param = os.sched_getparam(0)
    old_cpus = os.sched_getaffinity(0)
    locked = False
    try:
        if cfg.priority is not None:
            lo, hi = os.sched_get_priority_min(os.SCHED_FIFO), os.sched_get_priority_max(os.SCHED_FIFO)
            if not lo <= cfg.priority <= hi:
                refuse(f"SCHED_FIFO priority {cfg.priority} is outside {lo}..{hi}")
            else:
                try:
                    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(cfg.priority))
                    state.applied.append(f"SCHED_FIFO priority {cfg.priority}")
                except PermissionError:
                    refuse(
                        f"SCHED_FIFO priority {cfg.priority} refused (EPERM): needs CAP_SYS_NICE (root) or an "
                        f"rtprio limit of at least {cfg.priority} (ulimit -r; now {_limit(resource.RLIMIT_RTPRIO)})"
                    )
        if cfg.cpu is not None:
            n = os.cpu_count() or 1
            if not 0 <= cfg.cpu < n:
                refuse(f"CPU {cfg.cpu} does not exist (this machine has CPUs 0-{n - 1})")
            else:
                try:
                    os.sched_setaffinity(0, {cfg.cpu})
                    state.applied.append(f"pinned to CPU {cfg.cpu}")
                except OSError as exc:
                    refuse(
                        f"pinning to CPU {cfg.cpu} refused ({exc.strerror}): is it in this process's cpuset?"
                    )
        if cfg.lock_memory:
            libc = _libc()
            if libc.mlockall(MCL_CURRENT | MCL_FUTURE) != 0:
                err = ctypes.get_errno()
                refuse(
                    f"mlockall refused ({errno.errorcode.get(err, err)}): needs CAP_IPC_LOCK (root) or a "
                    f"locked-memory limit above the process size (ulimit -l; now {_limit(resource.RLIMIT_MEMLOCK)})"
                )
            else:
                locked = True
                _prefault(cfg)
                state.applied.append(
                    f"memory locked (mlockall), {cfg.prefault_heap_mb} MiB of heap prefaulted"
                )
        yield state
    finally:
        if locked:
            _libc().munlockall()
        if os.sched_getaffinity(0) != old_cpus:
            os.sched_setaffinity(0, old_cpus)
        if os.sched_getscheduler(0) != old_policy or os.sched_getparam(0) != old_param:
            os.sched_setscheduler(0, old_policy, old_param)
