"""What this process may do, asked of the kernel rather than guessed from the user id.

Root in a container often lacks CAP_SYS_NICE and CAP_IPC_LOCK; an unprivileged user may hold
CAP_NET_RAW on the interpreter or a high ``ulimit -r``. So: the effective capability set from
``/proc/self/status`` (``CapEff``) for what is a plain capability (veth pairs, raw sockets), and a
probe for what a capability alone does not decide (SCHED_FIFO: also RLIMIT_RTPRIO and the cgroup's
real-time budget; mlockall: also RLIMIT_MEMLOCK). Each answer comes with the reason when it is no.
"""

from __future__ import annotations

import os
import resource
import subprocess
import sys
import threading

# capability numbers (linux/capability.h)
CAP_SETGID = 6
CAP_SETUID = 7
CAP_NET_ADMIN = 12
CAP_NET_RAW = 13
CAP_IPC_LOCK = 14
CAP_SYS_NICE = 23
NAMES = {
    CAP_SETGID: "CAP_SETGID",
    CAP_SETUID: "CAP_SETUID",
    CAP_NET_ADMIN: "CAP_NET_ADMIN",
    CAP_NET_RAW: "CAP_NET_RAW",
    CAP_IPC_LOCK: "CAP_IPC_LOCK",
    CAP_SYS_NICE: "CAP_SYS_NICE",
}


def effective() -> int:
    """The effective capability set of this process (the ``CapEff`` bit mask); 0 when unreadable."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("CapEff:"):
                    return int(line.split()[1], 16)
    except OSError:
        pass
    return 0


def missing(*caps: int) -> list[str]:
    """The names of those of ``caps`` this process does not hold (empty: it holds them all)."""
    have = effective()
    return [NAMES.get(c, f"capability {c}") for c in caps if not have >> c & 1]


def fifo_refused(priority: int) -> str | None:
    """Why SCHED_FIFO at ``priority`` is refused here, or None when it is allowed.

    Tried on a short-lived thread (a policy is per thread), so the caller's own policy never changes.
    """
    result: list[str | None] = []

    def probe() -> None:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
            result.append(None)
        except OSError as exc:
            result.append(f"SCHED_FIFO priority {priority} refused ({exc.strerror})")

    t = threading.Thread(target=probe, name="fieldbus-fifo-probe")
    t.start()
    t.join()
    return result[0] if result else "the probe thread did not report"


_MLOCK_PROBE = (
    "import ctypes, sys\n"
    "libc = ctypes.CDLL(None, use_errno=True)\n"
    "sys.exit(0 if libc.mlockall(3) == 0 else ctypes.get_errno())\n"  # MCL_CURRENT | MCL_FUTURE
)


def memory_lock_refused() -> str | None:
    """Why mlockall(MCL_CURRENT | MCL_FUTURE) is refused here, or None when it is allowed.

    Allowed with CAP_IPC_LOCK or an unlimited RLIMIT_MEMLOCK whatever the process size; under a
    finite limit it is tried in a child interpreter (the caller's memory stays unlocked), whose
    size is that of a bare Python process: a bigger caller may still be refused.
    """
    if not missing(CAP_IPC_LOCK) or resource.getrlimit(resource.RLIMIT_MEMLOCK)[0] == resource.RLIM_INFINITY:
        return None
    res = subprocess.run([sys.executable, "-c", _MLOCK_PROBE], capture_output=True, check=False)
    if res.returncode == 0:
        return None
    return f"mlockall refused ({os.strerror(res.returncode)})"
