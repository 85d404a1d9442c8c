"""Real-time settings for the thread that runs the cycle: SCHED_FIFO, CPU affinity, locked memory.

What every real-time Linux master relies on (SOEM on PREEMPT_RT, IgH,
ros2_control): the cycle thread at a fixed real-time priority, pinned to a CPU,
its memory locked so that no page fault stalls a cycle. :func:`realtime`
applies what :class:`RtConfig` asks for and restores the previous settings on
exit. A setting the system refuses gives one line naming the capability or
limit it needs (or, with ``strict``, an :class:`RtError`); the others still
apply.

Scheduling and affinity apply to the calling thread (Linux: ``pid 0``);
``mlockall`` to the whole process. Threads the cycle thread starts afterwards
(Cyclone DDS's receive and event threads, a recorder's writer) inherit its
SCHED_FIFO priority; :func:`rank_below` then puts every other thread of the
process one priority under the cycle, so that the cycle preempts them when it
wakes while they still preempt normal work. Prefaulting touches ``prefault_heap_mb`` of
heap once, so the allocator's pages are mapped and locked before the cycle
needs them (Python 3.11 keeps its frames on the heap; the thread's C stack is
locked as it stands by ``MCL_CURRENT`` and as it grows by ``MCL_FUTURE``).
"""

from __future__ import annotations

import ctypes
import errno
import os
import resource
import threading
from collections.abc import Callable, Iterable, Iterator
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
    fifo: int | None = None  # the SCHED_FIFO priority the calling thread was given (None: none)
    cpus_before: set[int] | None = None  # the CPUs it was allowed before it was pinned (None: not pinned)
    # realtime(..., fifo_later=True): applies the asked SCHED_FIFO priority to the calling thread (once)
    _fifo_later: Callable[[], None] | None = field(default=None, repr=False)

    def to_json(self) -> dict[str, list[str]]:
        return {"applied": self.applied, "refused": self.refused}

    def start_fifo(self) -> None:
        """With ``realtime(..., fifo_later=True)``: give the calling thread its SCHED_FIFO priority now
        (a refusal as :func:`realtime` says one). Does nothing otherwise, or the second time."""
        start, self._fifo_later = self._fifo_later, None
        if start is not None:
            start()


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
def realtime(
    cfg: RtConfig, warn: Callable[[str], None] | None = None, *, fifo_later: bool = False
) -> Iterator[RtState]:
    """Apply ``cfg`` to the calling thread (and lock the process's memory); restore everything on exit.

    ``fifo_later``: the SCHED_FIFO priority is checked now but given when the caller says so
    (:meth:`RtState.start_fifo`), so that set-up work (seconds of Python: DDS topics, a network's
    bring-up) does not run at real-time priority. The kernel gives real-time threads
    ``sched_rt_runtime_us`` of every ``sched_rt_period_us`` on a CPU (950 ms of 1 s by default) and
    stops them for the rest of the period when they use more: a busy set-up at SCHED_FIFO used most of
    its second and the first cycles were throttled (a 38 ms gap at cycle 19 of ``fieldbus serve``).
    """
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
            elif fifo_later:
                priority = cfg.priority
                state._fifo_later = lambda: _fifo(priority, state, refuse)
            else:
                _fifo(cfg.priority, state, refuse)
        if cfg.cpu is not None:
            n = os.cpu_count() or 1
            if not 0 <= cfg.cpu < n:
                refuse(f"CPU {cfg.cpu} does not exist (this machine has CPUs 0-{n - 1})")
            else:
                try:
                    os.sched_setaffinity(0, {cfg.cpu})
                    state.applied.append(f"pinned to CPU {cfg.cpu}")
                    state.cpus_before = set(old_cpus)
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


def _fifo(priority: int, state: RtState, refuse: Callable[[str], None]) -> None:
    """SCHED_FIFO ``priority`` for the calling thread, noted in ``state`` (or refused, saying why)."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        state.applied.append(f"SCHED_FIFO priority {priority}")
        state.fifo = priority
    except PermissionError:
        refuse(
            f"SCHED_FIFO priority {priority} refused (EPERM): needs CAP_SYS_NICE (root) or an "
            f"rtprio limit of at least {priority} (ulimit -r; now {_limit(resource.RLIMIT_RTPRIO)})"
        )


def thread_ids() -> list[int]:
    """The native ids of this process's threads (Linux: ``/proc/self/task``)."""
    return sorted(int(t) for t in os.listdir("/proc/self/task"))


def rank_below(priority: int) -> str:
    """Every other thread of this process at real-time priority ``priority`` or above to one below it.

    The calling thread (the cycle, at SCHED_FIFO ``priority``) keeps its own. A thread at ``priority``
    cannot preempt a thread of the same priority that is running (SCHED_FIFO runs it until it blocks); one
    below, the cycle preempts it at once when its deadline comes, and it still preempts normal work.
    Priority 1 has nothing below it in SCHED_FIFO: the others then go to SCHED_OTHER. Threads at a lower
    real-time priority or at normal priority stay as they are. Returns the line for :attr:`RtState.applied`.
    """
    me = threading.get_native_id()
    policy, param = (os.SCHED_FIFO, priority - 1) if priority > 1 else (os.SCHED_OTHER, 0)

    def at_or_above(tid: int) -> bool:
        return _real_time(tid) and os.sched_getparam(tid).sched_priority >= priority

    return _move_threads((t for t in thread_ids() if t != me), at_or_above, policy, param)


def raise_threads(tids: Iterable[int], priority: int, *, where: str = "below the cycle") -> str:
    """The threads ``tids`` of this process (made at normal priority: a DDS participant's receive and
    event threads) to SCHED_FIFO ``priority``, so that they still preempt normal work (under priority 1
    they stay as they are). Returns the line for :attr:`RtState.applied` (``where``: their place beside
    the cycle's priority, in words)."""
    if priority < 1:
        return "other threads left at normal priority (nothing is below SCHED_FIFO 1)"
    return _move_threads(tids, lambda tid: not _real_time(tid), os.SCHED_FIFO, priority, where)


def _real_time(tid: int) -> bool:
    return os.sched_getscheduler(tid) in (os.SCHED_FIFO, os.SCHED_RR)


def _move_threads(
    tids: Iterable[int],
    chosen: Callable[[int], bool],
    policy: int,
    param: int,
    where: str = "below the cycle",
) -> str:
    """Each of ``tids`` that is ``chosen`` to ``policy`` at priority ``param``; a thread that ended
    meanwhile is passed over, a refusal counted. Returns the line for :attr:`RtState.applied`."""
    moved, refused = 0, 0
    for tid in tids:
        try:
            if chosen(tid):
                os.sched_setscheduler(tid, policy, os.sched_param(param))
                moved += 1
        except ProcessLookupError:  # the thread ended meanwhile
            continue
        except PermissionError:
            refused += 1
    to = f"SCHED_FIFO priority {param}" if policy == os.SCHED_FIFO else "SCHED_OTHER"
    left = f" ({refused} refused: EPERM)" if refused else ""
    return f"{moved} other thread(s) {where}: {to}{left}"


def unpin_others(cpus: set[int]) -> str:
    """Every other thread of this process allowed on ``cpus`` again (the CPUs before the cycle was pinned).

    Threads the pinned cycle thread started inherit its one CPU: every real-time thread of the process
    would then share it with the cycle (and with its RT throttling budget). Returns the applied line.
    """
    me = threading.get_native_id()
    moved = 0
    for tid in thread_ids():
        if tid == me:
            continue
        try:
            if os.sched_getaffinity(tid) != cpus:
                os.sched_setaffinity(tid, cpus)
                moved += 1
        except (ProcessLookupError, PermissionError):
            continue
    return f"{moved} other thread(s) allowed on CPUs {','.join(map(str, sorted(cpus)))}"
