"""Scheduling priority: which kernel threads count as tty workers, raising each new one once, and a
process's threads going real-time (checked in a child process: the test runner keeps its policy)."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from shared.realtime import KTHREADD_PID, TtyWorkers, is_tty_worker, tty_worker_pids

ROOT = Path(__file__).resolve().parents[2]


def fake_thread(proc: Path, pid: int, comm: str, ppid: int) -> None:
    d = proc / str(pid)
    d.mkdir(parents=True, exist_ok=True)
    (d / "comm").write_text(comm + "\n")
    (d / "stat").write_text(f"{pid} ({comm}) S {ppid} 0 0 0 -1 69238880 0 0 0 0 0 0 0 0 20 0 1 0\n")


def fake_proc(tmp_path: Path, threads: dict[int, tuple[str, int]]) -> Path:
    """A /proc with kthreadd listing its children, and the given (comm, ppid) threads."""
    proc = tmp_path / "proc"
    fake_thread(proc, KTHREADD_PID, "kthreadd", 0)
    for pid, (comm, ppid) in threads.items():
        fake_thread(proc, pid, comm, ppid)
    kids = [pid for pid, (_, ppid) in threads.items() if ppid == KTHREADD_PID]
    task = proc / str(KTHREADD_PID) / "task" / str(KTHREADD_PID)
    task.mkdir(parents=True)
    (task / "children").write_text(" ".join(map(str, kids)) + " ")
    return proc


def test_only_kernel_threads_named_kworker_u_are_tty_workers(tmp_path):
    proc = fake_proc(tmp_path, {
        10: ("kworker/u8:3-events_unbound", KTHREADD_PID),
        11: ("kworker/u9:0", KTHREADD_PID),
        12: ("kworker/0:1H-kblockd", KTHREADD_PID),  # bound to a CPU: not the tty layer's
        13: ("kworker/R-rcu_gp", KTHREADD_PID),  # a rescuer
        14: ("ksoftirqd/0", KTHREADD_PID),
        500: ("kworker/u8:1 (fake)", 1),  # a user process naming itself so
    })
    assert tty_worker_pids(proc) == [10, 11]
    assert is_tty_worker(500, proc) is False
    assert is_tty_worker(999, proc) is None  # gone


def test_each_new_worker_is_raised_once_and_an_unnamed_one_is_looked_at_again(tmp_path):
    proc = fake_proc(tmp_path, {10: ("kworker/u8:0-events_unbound", KTHREADD_PID),
                                11: ("kworker/u8:1", KTHREADD_PID), 12: ("ksoftirqd/0", KTHREADD_PID)})
    policy = {10: os.SCHED_OTHER, 11: os.SCHED_FIFO, 12: os.SCHED_OTHER}  # 11: raised by someone else
    calls = []

    def setscheduler(pid: int, pol: int, param: os.sched_param) -> None:
        calls.append((pid, pol, param.sched_priority))
        policy[pid] = pol

    workers = TtyWorkers(7, proc, getscheduler=policy.__getitem__, setscheduler=setscheduler)
    assert workers.raise_new() == 1
    assert calls == [(10, os.SCHED_FIFO, 7)]
    assert workers.raise_new() == 0  # nothing new
    # the kernel starts a worker: it shows up as "kthreadd" until it has its name
    fake_thread(proc, 20, "kthreadd", KTHREADD_PID)
    policy[20] = os.SCHED_OTHER
    (proc / "2" / "task" / "2" / "children").write_text("10 11 12 20 ")
    assert workers.raise_new() == 0
    fake_thread(proc, 20, "kworker/u8:2", KTHREADD_PID)
    assert workers.raise_new() == 1
    assert calls[-1] == (20, os.SCHED_FIFO, 7)
    assert workers.raised == 2


def test_a_refusal_is_kept_and_nothing_counts_as_raised(tmp_path):
    proc = fake_proc(tmp_path, {10: ("kworker/u8:0", KTHREADD_PID)})

    def refuse(pid: int, pol: int, param: os.sched_param) -> None:
        raise PermissionError(1, "Operation not permitted")

    workers = TtyWorkers(7, proc, getscheduler=lambda pid: os.SCHED_OTHER, setscheduler=refuse)
    assert workers.raise_new() == 0
    assert workers.refused == "Operation not permitted"
    assert workers.raised == 0


CHILD = textwrap.dedent("""
    import logging, os, threading
    from shared.realtime import raise_process_priority
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except OSError:
        print("refused"); raise SystemExit
    stop = threading.Event()
    waiting = threading.Thread(target=stop.wait, daemon=True)
    waiting.start()
    raised = raise_process_priority("test", logging.getLogger("t"), rt_priority=2)
    policies = [os.sched_getscheduler(0), os.sched_getscheduler(waiting.native_id)]
    later = threading.Thread(target=lambda: policies.append(os.sched_getscheduler(0)), daemon=True)
    later.start()
    later.join()
    stop.set()
    print("raised", raised, "fifo", [p == os.SCHED_FIFO for p in policies])
""")


def test_raise_process_priority_puts_every_thread_and_later_ones_at_real_time():
    out = subprocess.run([sys.executable, "-c", CHILD], capture_output=True, text=True, timeout=60, cwd=ROOT,
                         env={**os.environ, "PYTHONPATH": str(ROOT)}).stdout
    if out.strip() == "refused":
        pytest.skip("real-time scheduling not permitted here")
    assert out.strip() == "raised 2 fifo [True, True, True]"  # main, waiting, and the thread started later


LOCK_CHILD = textwrap.dedent("""
    import logging
    from shared.realtime import lock_memory
    locked = lock_memory("test", logging.getLogger("t"))
    status = open("/proc/self/status").read()
    vmlck = [line.split()[1] for line in status.splitlines() if line.startswith("VmLck:")]
    big = bytearray(8 << 20)  # touched after the call: locked because of MCL_FUTURE | MCL_ONFAULT
    status = open("/proc/self/status").read()
    after = [line.split()[1] for line in status.splitlines() if line.startswith("VmLck:")]
    print(locked, vmlck[0] if vmlck else "-", after[0] if after else "-", len(big))
""")


def test_lock_memory_locks_pages_touched_later_or_says_why_not():
    out = subprocess.run([sys.executable, "-c", LOCK_CHILD], capture_output=True, text=True, timeout=60, cwd=ROOT,
                         env={**os.environ, "PYTHONPATH": str(ROOT)})
    locked, before, after, _ = out.stdout.split()
    if locked == "False":
        assert "memory stays pageable" in out.stderr
        return
    assert int(after) - int(before) >= 8 << 10  # kB: the 8 MiB buffer touched after the call


def test_can_lower_nice_reads_cap_sys_nice_from_the_effective_set(tmp_path):
    from shared.realtime import can_lower_nice

    status = tmp_path / "status"
    status.write_text("Name:\tx\nCapEff:\t0000000000800000\n")  # bit 23 only
    assert can_lower_nice(status)
    status.write_text("Name:\tx\nCapEff:\t00000000007fffff\n")  # every bit below it
    assert not can_lower_nice(status)
    assert not can_lower_nice(tmp_path / "missing")
