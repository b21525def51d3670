"""Scheduling priority for the threads that must keep up with a device while the host is busy.

Device readers and the robot's command stream run on their own threads and ask for a real-time
policy (SCHED_FIFO) for the calling thread; where the OS refuses (no CAP_SYS_NICE, no RLIMIT_RTPRIO,
not Linux) they fall back to a raised nice value, and where that is refused too they keep the normal
priority. Either way one log line says what the thread got, so a loaded host that loses frames can
be told apart from one that was never allowed to prioritise them.

A reader at real-time priority is not enough on its own: the kernel's tty layer hands every chunk
a serial port or pty receives to a worker thread of its unbound workqueue (``kworker/u*``, normal
priority), which moves it to the line discipline and only then wakes the reader. With one CPU-bound
process per core that worker waits tens of milliseconds for a CPU; ``raise_tty_workers`` gives
those kernel threads a real-time priority too (``TtyWorkers``; host-wide: every unbound kernel work
item runs there).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import errno
import gc
import logging
import os
import sys
import threading
from collections.abc import Callable
from pathlib import Path

GIL_SWITCH_S = 0.0005  # Python's default 5 ms would let any other thread hold up a real-time one that long
DEFAULT_RT_PRIORITY = 10  # above every normal thread, below the kernel's own real-time threads (50)
FALLBACK_NICE = -10
TTY_WORKER_RT_PRIORITY = 9  # the kernel threads that feed the readers: just below them
KTHREADD_PID = 2  # parent of every kernel thread
# mlockall flags (linux/mman.h): pages mapped now, pages mapped later, each locked when first touched
MCL_CURRENT, MCL_FUTURE, MCL_ONFAULT = 1, 2, 4


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


def raise_process_priority(what: str, log: logging.Logger, nice: int = FALLBACK_NICE, rt_priority: int = 0) -> int:
    """Every thread of this process that runs at the normal policy (the event loop, Zenoh's threads)
    to SCHED_FIFO at ``rt_priority`` (0: skip), else to nice ``nice``: a real-time thread waiting for
    the GIL is otherwise held up as long as the thread holding it waits for a CPU behind other
    processes, and a message it publishes waits as long for Zenoh's threads to send it. Real time
    only for a process whose threads do little besides (real-time threads using most of a CPU get
    throttled by the kernel); threads they start later inherit the policy. Returns how many threads
    were raised; logs what was refused."""
    if not os.path.isdir("/proc/self/task") or not hasattr(os, "sched_setscheduler"):
        return 0
    raised, refused, policy = 0, "", ""
    for entry in os.listdir("/proc/self/task"):
        tid = int(entry)
        try:
            if os.sched_getscheduler(tid) != os.SCHED_OTHER:
                continue
        except OSError:  # the thread ended meanwhile
            continue
        if rt_priority > 0:
            try:
                os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(rt_priority))
                raised, policy = raised + 1, f"SCHED_FIFO priority {rt_priority}"
                continue
            except OSError as exc:
                refused = f"SCHED_FIFO {rt_priority}: {exc.strerror}"
        if nice >= 0:
            continue
        try:
            if os.getpriority(os.PRIO_PROCESS, tid) > nice:
                os.setpriority(os.PRIO_PROCESS, tid, nice)
                raised, policy = raised + 1, policy or f"nice {nice}"
        except OSError as exc:  # refused, or the thread ended meanwhile
            refused = exc.strerror or str(exc)
    if refused and not raised:
        log.warning("%s: the process's threads keep their priority (%s): a busy host can hold up its "
                    "real-time threads through the GIL", what, refused)
    else:
        log.info("%s: %d threads of the process at %s", what, raised, policy or "their priority")
    return raised


def autogroup_nice(pid: int | str = "self") -> int | None:
    """The nice value of a process's autogroup (Linux), or None where there is none to read."""
    try:
        return int(Path(f"/proc/{pid}/autogroup").read_text().split()[-1])  # "/autogroup-123 nice 0"
    except (OSError, ValueError, IndexError):
        return None


def shift_autogroup(pid: int | str, steps: int) -> int | None:
    """Moves a process's autogroup ``steps`` nice values (negative: a larger CPU share), clamped to
    -20..19; returns the new value, or None where the OS refused or has no autogroups."""
    current = autogroup_nice(pid)
    if current is None:
        return None
    target = min(19, max(-20, current + steps))
    try:
        Path(f"/proc/{pid}/autogroup").write_text(str(target))
    except OSError:
        return None
    return target


CAP_SYS_NICE = 23  # linux/capability.h


def can_lower_nice(status: Path = Path("/proc/self/status")) -> bool:
    """Whether this process may lower nice values (CAP_SYS_NICE in its effective set): raising a
    nice value is always allowed, taking it back needs this."""
    try:
        for line in status.read_text().splitlines():
            if line.startswith("CapEff:"):
                return bool(int(line.split()[1], 16) >> CAP_SYS_NICE & 1)
    except (OSError, ValueError, IndexError):
        pass
    return False


def raise_cpu_share(what: str, log: logging.Logger, steps: int) -> None:
    """A larger CPU share for this whole process against the host's other processes: its autogroup
    (Linux schedules each session as one, and every service is its own session) ``steps`` nice values
    lower, and its threads at nice ``-steps`` where autogroups are off. Logs what it got."""
    group = shift_autogroup("self", -steps)
    raise_process_priority(what, log, nice=-steps)
    if group is None:
        log.warning("%s: its autogroup keeps its CPU share (not permitted or not Linux): under CPU load it "
                    "may fall behind the services", what)
    else:
        log.info("%s: autogroup at nice %d", what, group)


def thread_schedstat() -> tuple[float, int]:
    """The calling thread's seconds spent runnable but waiting for a CPU, and how many times it has
    been put on a CPU (the kernel's schedstat; (0.0, 0) where it is not available). A thread that
    wakes from a timed wait and then has to wait for the GIL is put on a CPU twice."""
    try:
        with open("/proc/thread-self/schedstat", "rb") as f:
            fields = f.read().split()
        return int(fields[1]) * 1e-9, int(fields[2])
    except (OSError, IndexError, ValueError):
        return 0.0, 0


def lock_memory(what: str, log: logging.Logger) -> bool:
    """Keep every page this process touches in RAM (mlockall with MCL_ONFAULT: locked as touched, so
    untouched mappings cost nothing). Without it a real-time thread can stall for a disk read when
    the kernel has dropped a page of its code or data under page-cache pressure (a recording filling
    it), and any thread doing so while it holds the GIL stalls them all. Returns whether it held;
    a refusal (no CAP_IPC_LOCK and a small RLIMIT_MEMLOCK, not Linux) is logged."""
    name = ctypes.util.find_library("c") if sys.platform.startswith("linux") else None
    if name is None:
        log.info("%s: memory stays pageable (no mlockall on this OS)", what)
        return False
    libc = ctypes.CDLL(name, use_errno=True)
    if libc.mlockall(MCL_CURRENT | MCL_FUTURE | MCL_ONFAULT) == 0:
        log.info("%s: memory locked (mlockall, on fault)", what)
        return True
    err = ctypes.get_errno()
    log.warning("%s: memory stays pageable (mlockall: %s): a disk read after page-cache pressure can stall "
                "its real-time threads; give the service CAP_IPC_LOCK or raise RLIMIT_MEMLOCK to fix", what,
                os.strerror(err))
    return False


def kthread_pids(proc: Path = Path("/proc")) -> list[int]:
    """The kernel threads, from kthreadd's list of children ([] where the kernel does not list them)."""
    children = proc / str(KTHREADD_PID) / "task" / str(KTHREADD_PID) / "children"
    try:
        return [int(p) for p in children.read_text().split()]
    except (OSError, ValueError):
        return []


def is_tty_worker(pid: int, proc: Path = Path("/proc")) -> bool | None:
    """Whether ``pid`` is one of the kernel's unbound workqueue workers (a kernel thread named
    ``kworker/u...``), which run the tty layer's receive work; None while a new kernel thread has
    not got its name yet (or it has ended)."""
    try:
        comm = (proc / str(pid) / "comm").read_text().strip()
        if comm == "kthreadd" and pid != KTHREADD_PID:  # just forked: named in a moment
            return None
        if not comm.startswith("kworker/u"):
            return False
        stat = (proc / str(pid) / "stat").read_text()
    except OSError:
        return None
    # "pid (comm) state ppid ...": comm may hold spaces and parentheses, so split after the last ")"
    fields = stat[stat.rfind(")") + 1:].split()
    return len(fields) > 1 and fields[1] == str(KTHREADD_PID)  # a kernel thread, not a process named so


def tty_worker_pids(proc: Path = Path("/proc")) -> list[int]:
    """The kernel's unbound workqueue workers now: kthreadd's children, else all of /proc."""
    pids = kthread_pids(proc) or [int(e.name) for e in os.scandir(proc) if e.name.isdigit()]
    return [pid for pid in pids if is_tty_worker(pid, proc)]


class TtyWorkers:
    """Keeps the kernel's tty workers (``tty_worker_pids``) at SCHED_FIFO ``rt_priority``: the kernel
    starts new ones as it needs them, so ``raise_new`` is called every fraction of a second; it
    reads only kthreadd's list of children and looks closer at the threads it has not seen."""

    def __init__(self, rt_priority: int = TTY_WORKER_RT_PRIORITY, proc: Path = Path("/proc"),
                 getscheduler: Callable[[int], int] | None = None,
                 setscheduler: Callable[[int, int, os.sched_param], None] | None = None) -> None:
        self.rt_priority = rt_priority
        self.proc = proc
        # replaceable: tests must not touch real threads
        self._get = getscheduler or getattr(os, "sched_getscheduler", None)
        self._set = setscheduler or getattr(os, "sched_setscheduler", None)
        self.seen: set[int] = set()
        self.raised = 0
        self.refused = ""  # the last refusal's error

    def raise_new(self) -> int:
        """Raise the workers started since the last call (those another process raised are left as
        they are); returns how many were raised."""
        if self._get is None or self._set is None or not self.proc.is_dir():
            self.refused = "no real-time scheduling or /proc on this OS"
            return 0
        raised = 0
        kthreads = set(kthread_pids(self.proc))
        if not kthreads:  # the kernel does not list kthreadd's children: look at every worker each time
            self.seen = set()
        unnamed = set()
        for pid in sorted(kthreads - self.seen) if kthreads else tty_worker_pids(self.proc):
            worker = is_tty_worker(pid, self.proc)
            if worker is None:
                unnamed.add(pid)  # look again next time
            if not worker:
                continue
            try:
                if self._get(pid) == os.SCHED_OTHER:
                    self._set(pid, os.SCHED_FIFO, os.sched_param(self.rt_priority))
                    raised += 1
            except OSError as exc:  # refused, or the worker ended meanwhile
                if exc.errno != errno.ESRCH:
                    self.refused = exc.strerror or str(exc)
        self.seen = kthreads - unnamed
        self.raised += raised
        return raised
