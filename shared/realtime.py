"""Scheduling priority for the threads that must keep up with a device while the host is busy.

Device readers and the robot's command stream run on their own threads and ask for a real-time
policy (SCHED_FIFO) for the calling thread; where the OS refuses (no CAP_SYS_NICE, no RLIMIT_RTPRIO,
not Linux) they fall back to a raised nice value, and where that is refused too they keep the normal
priority. Either way one log line says what the thread got, so a loaded host that loses frames can
be told apart from one that was never allowed to prioritise them.
"""

from __future__ import annotations

import gc
import logging
import os
import sys
import threading

GIL_SWITCH_S = 0.0005  # Python's default 5 ms would let any other thread hold up a real-time one that long
DEFAULT_RT_PRIORITY = 10  # above every normal thread, below the kernel's own real-time threads (50)
FALLBACK_NICE = -10


def raise_priority(what: str, log: logging.Logger, rt_priority: int = DEFAULT_RT_PRIORITY,
                   nice: int = FALLBACK_NICE) -> str:
    """Give the calling thread SCHED_FIFO at ``rt_priority`` (0: skip), else ``nice``; returns
    "fifo", "nice" or "normal" and logs the outcome."""
    tid = threading.get_native_id()
    # A real-time thread still needs the GIL: ask other threads of the process to hand it over sooner,
    # and move what the service built at start out of the collector's reach (a full collection over
    # it holds the GIL for ~10 ms).
    sys.setswitchinterval(min(sys.getswitchinterval(), GIL_SWITCH_S))
    gc.freeze()
    errors = []
    if rt_priority > 0 and hasattr(os, "sched_setscheduler"):
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(rt_priority))  # 0: the calling thread
            log.info("%s: thread %d runs SCHED_FIFO priority %d", what, tid, rt_priority)
            return "fifo"
        except (OSError, ValueError) as exc:
            errors.append(f"SCHED_FIFO {rt_priority}: {exc.strerror if isinstance(exc, OSError) else exc}")
    if nice < 0 and hasattr(os, "setpriority"):
        try:
            os.setpriority(os.PRIO_PROCESS, tid, nice)  # Linux: a thread id sets that thread only
            log.warning("%s: thread %d runs at nice %d (%s not permitted): under heavy CPU load it may "
                        "still be late", what, tid, nice, "; ".join(errors) or "real-time policy")
            return "nice"
        except OSError as exc:
            errors.append(f"nice {nice}: {exc.strerror}")
    log.warning("%s: thread %d runs at normal priority (%s not permitted): under CPU load device data may be "
                "late or lost; give the service CAP_SYS_NICE or an RLIMIT_RTPRIO to fix", what, tid,
                "; ".join(errors) or "priority change")
    return "normal"


def raise_process_priority(what: str, log: logging.Logger, nice: int = FALLBACK_NICE) -> int:
    """Nice ``nice`` for every thread of this process that runs at the normal policy (the event loop,
    Zenoh's threads): a real-time thread waiting for the GIL is otherwise held up as long as the
    thread holding it waits for a CPU behind other processes. Nice, not real time: these threads do
    the service's bulk work, and real-time threads using most of a CPU get throttled by the kernel.
    Returns how many threads were raised; logs what was refused."""
    if nice >= 0 or not hasattr(os, "setpriority") or not os.path.isdir("/proc/self/task"):
        return 0
    raised, refused = 0, ""
    for entry in os.listdir("/proc/self/task"):
        tid = int(entry)
        try:
            if os.sched_getscheduler(tid) == os.SCHED_OTHER and os.getpriority(os.PRIO_PROCESS, tid) > nice:
                os.setpriority(os.PRIO_PROCESS, tid, nice)
                raised += 1
        except OSError as exc:  # refused, or the thread ended meanwhile
            refused = exc.strerror or str(exc)
    if refused and not raised:
        log.warning("%s: the process's threads keep their priority (%s): a busy host can hold up its "
                    "real-time threads through the GIL", what, refused)
    else:
        log.info("%s: %d threads of the process at nice %d", what, raised, nice)
    return raised
