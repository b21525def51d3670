"""A tiny process that timestamps what the host writes to a simulated device's pty.

``python arrival_stamper.py MASTER_FD SLAVE_FD [PROBE_PERIOD_S]`` (standard library only, inherited
fds): reads the pty master as bytes arrive and writes each read to stdout as
``<seconds: f8><length: u4><bytes>``, and with length 0 a *horizon*: every byte the host wrote
before that monotonic time has been delivered in earlier records.

Why probes: a pty does not hand bytes from the slave to the master in the writer's context; the
kernel queues the transfer to a worker thread (``flush_to_ldisc`` on an unbound kworker) of normal
priority. On a busy host that worker waits behind every runnable process, and the host's commands
reach the master 10 ms to over 1 s after they were written, in bunches, although the writer and
this reader both run SCHED_FIFO (a USB serial adapter submits the host's bytes in the writer's
context, and a real board's UART sees them within about a millisecond). Stamping reads with the
read time would show the board gaps the host never left. So every ``PROBE_PERIOD_S`` this process
writes a marker (``PROBE``) into the slave side itself, which the kernel queues in order behind
what the host wrote before it. A read is stamped with the write time of the oldest probe still in
flight (the bytes were written before it), or with the read time if none is: an upper bound on
when the host wrote them that is at most one probe period late however long the transfer took.
Each probe read back is a horizon; the simulated board judges its watchdog no further than that
(services/world/devices.py), so it brakes on the host's silence, not on the pty's.

It runs SCHED_FIFO where the OS allows and shares no GIL with the world, whose main thread is busy
stepping the physics and, on a loaded host, waits for a CPU while holding the GIL.
"""

from __future__ import annotations

import collections
import gc
import os
import select
import struct
import sys
import time

HEADER = struct.Struct("<dI")
PROBE = b"\xa5\x5axm-probe\xc3\x3c\x96\x69\x0f\xf0"  # 16 bytes no host frame contains by chance (2^-128)
PROBE_PERIOD_S = 0.001
MAX_PROBES_IN_FLIGHT = 1000  # 16 kB of the pty's 64 kB buffer: the rest stays the host's
PARENT_CHECK_S = 1.0


class ProbeSplitter:
    """Pure: splits the master's byte stream into the host's bytes and the probes read back.

    ``sent(t_before, t_after)`` records a probe written between those times; ``feed(data, now)``
    returns ``[(stamp, bytes)]`` of host data and ``(stamp, b"")`` horizons, in stream order. A tail
    that may be the start of a probe waits for the next read."""

    def __init__(self) -> None:
        self.in_flight: collections.deque[tuple[float, float]] = collections.deque()
        self._buf = b""

    def sent(self, t_before: float, t_after: float) -> None:
        self.in_flight.append((t_before, t_after))

    def _stamp(self, now: float) -> float:
        return min(now, self.in_flight[0][1]) if self.in_flight else now

    def feed(self, data: bytes, now: float) -> list[tuple[float, bytes]]:
        buf, out = self._buf + data, []
        while (i := buf.find(PROBE)) >= 0:
            if i:
                out.append((self._stamp(now), buf[:i]))
            buf = buf[i + len(PROBE):]
            if self.in_flight:  # a probe we did not send (none in flight) is only data we drop
                out.append((self.in_flight.popleft()[0], b""))
        keep = next((k for k in range(min(len(PROBE) - 1, len(buf)), 0, -1) if PROBE.startswith(buf[-k:])), 0)
        if len(buf) > keep:
            out.append((self._stamp(now), buf[:len(buf) - keep]))
        self._buf = buf[len(buf) - keep:]
        return out


def _raise_priority() -> None:
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(10))
    except (OSError, AttributeError):
        try:
            os.setpriority(os.PRIO_PROCESS, 0, -10)
        except OSError:
            pass  # normal priority: stamps get later on a busy host, the probes still bound them


def _probe(fd: int, splitter: ProbeSplitter) -> None:
    if len(splitter.in_flight) >= MAX_PROBES_IN_FLIGHT:
        return  # the transfer is stalled: the probes in flight already bound what waits behind them
    t0 = time.monotonic()
    try:
        n = os.write(fd, PROBE)
    except OSError:  # full (EAGAIN) or gone: no probe this period
        return
    if n == len(PROBE):
        splitter.sent(t0, time.monotonic())
    # a partial probe (the pty's buffer is full) never matches: its bytes reach the decoder as garbage


def main(master: int, slave: int, period: float = PROBE_PERIOD_S) -> None:
    gc.disable()  # nothing here makes cycles: no collector pauses
    _raise_priority()
    os.set_blocking(slave, False)
    out = sys.stdout.buffer.raw if hasattr(sys.stdout.buffer, "raw") else sys.stdout.buffer
    world = os.getppid()
    splitter = ProbeSplitter()
    next_probe = next_check = time.monotonic()
    while True:
        now = time.monotonic()
        if now >= next_check:  # the probes keep the pty busy: ask whether the world still runs
            if os.getppid() != world:
                return
            next_check = now + PARENT_CHECK_S
        if now >= next_probe:
            _probe(slave, splitter)
            next_probe = max(next_probe + period, now)
        try:
            ready, _, _ = select.select([master], [], [], max(0.0, next_probe - time.monotonic()))
            data = os.read(master, 1 << 16) if ready else b""
        except BlockingIOError:
            continue
        except OSError:  # the pty is gone
            time.sleep(0.02)
            continue
        if not data:
            continue
        records = b"".join(HEADER.pack(t, len(b)) + b for t, b in splitter.feed(data, time.monotonic()))
        try:
            out.write(records)
        except BrokenPipeError:
            return


if __name__ == "__main__":
    main(int(sys.argv[1]), int(sys.argv[2]), float(sys.argv[3]) if len(sys.argv) > 3 else PROBE_PERIOD_S)
