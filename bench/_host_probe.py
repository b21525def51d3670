"""The host under the chaos soak (bench/soak.py): a real-time probe that tells host stalls from the
cell's own, the hypervisor's steal time, I/O pressure and real-time threads of other processes."""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path

PROBE_RT_PRIORITY = 20  # above the cell's real-time threads (10)
HOST_STALL_MATCH_S = 0.05  # a command gap and a probe stall that end this close are one host stall


def steal_jiffies() -> list[int]:
    """Per CPU, the time the hypervisor ran something else while this (virtual) CPU had work, in
    1/100 s (/proc/stat's steal column; [] where not reported)."""
    try:
        lines = Path("/proc/stat").read_text().splitlines()
        return [int(line.split()[8]) for line in lines if line.startswith("cpu") and line[3] != " "]
    except (OSError, IndexError, ValueError):
        return []


def stall_probe(stop: threading.Event, t0: float, out: list, period: float = 0.004,
                threshold: float = 0.008) -> None:
    """A real-time thread of the soak itself (above the cell's) that sleeps ``period`` and records
    every wake-up later than ``threshold`` with the hypervisor's steal time per CPU over the last
    ~0.25 s: when the probe is late too, the host stalled, not the cell's threads; steal says the
    virtual machine's CPUs were taken away."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(PROBE_RT_PRIORITY))
    except (OSError, AttributeError):
        out.append({"error": "no real-time priority: the probe's lateness means little"})
    next_t = last_read = time.monotonic()
    steal = steal_jiffies()
    while not stop.is_set():
        next_t += period
        delay = next_t - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        now = time.monotonic()
        late = now - next_t
        if late > threshold:
            stolen = [(b - a) * 10 for a, b in zip(steal, steal_jiffies(), strict=False)]
            out.append({"t": round(now - t0, 2), "at_unix": round(time.time(), 3), "late_ms": round(late * 1e3, 1),
                        "steal_ms_per_cpu": stolen})
        if now - last_read > 0.25:
            steal, last_read = steal_jiffies(), now
        if late > period:
            next_t = time.monotonic()


def io_pressure() -> float | None:
    """Share of the last 10 s in which some task waited for I/O (%; None where not reported)."""
    try:
        return float(Path("/proc/pressure/io").read_text().split()[1].split("=")[1])
    except (OSError, IndexError, ValueError):
        return None


def foreign_rt_threads(cell: set[int]) -> int:
    """Real-time threads of user processes outside ``cell`` (another cell or test beside the soak
    competes with the robot's command stream at the same priority)."""
    n = 0
    for pid in filter(str.isdigit, os.listdir("/proc")):
        if int(pid) in cell:
            continue
        try:
            if not Path(f"/proc/{pid}/cmdline").read_bytes():  # a kernel thread
                continue
            for tid in os.listdir(f"/proc/{pid}/task"):
                n += os.sched_getscheduler(int(tid)) in (os.SCHED_FIFO, os.SCHED_RR)
        except OSError:
            continue
    return n


def attribute_brakes(events: list[dict], stalls: list[dict]) -> int:
    """Marks each brake event whose command gap (the robot service's ``host_gap``) ended within
    HOST_STALL_MATCH_S of a probe stall (``host_stall_near``; ``hypervisor_steal_near`` when that
    stall saw steal time); returns how many brakes no host stall explains."""
    for e in events:
        at = (e.get("host_gap") or {}).get("at_unix")
        near = [s for s in stalls if at is not None and abs(s.get("at_unix", 0.0) - at) < HOST_STALL_MATCH_S]
        e["host_stall_near"] = bool(near)
        e["hypervisor_steal_near"] = any(any(s.get("steal_ms_per_cpu", [])) for s in near)
    return sum(not e["host_stall_near"] for e in events)
