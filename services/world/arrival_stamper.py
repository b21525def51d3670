"""A tiny process that timestamps what the host writes to a simulated device's pty.

``python arrival_stamper.py FD`` (standard library only): reads the pty master ``FD`` (inherited) as bytes
arrive and writes each read to stdout as ``<monotonic seconds: f8><length: u4><bytes>``. It runs
SCHED_FIFO where the OS allows and shares no GIL with the world, whose main thread is busy
stepping the physics and, on a loaded host, waits for a CPU while holding the GIL: a reader thread
inside the world would stamp commands when it gets the GIL back, bunched, and the simulated
board's watchdog would see gaps the host never left (services/world/devices.py).
"""

from __future__ import annotations

import gc
import os
import select
import struct
import sys
import time

HEADER = struct.Struct("<dI")


def main(fd: int) -> None:
    gc.disable()  # nothing here makes cycles: no collector pauses
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(10))
    except (OSError, AttributeError):
        try:
            os.setpriority(os.PRIO_PROCESS, 0, -10)
        except OSError:
            pass  # the world logs the outcome from the first line below
    out = sys.stdout.buffer.raw if hasattr(sys.stdout.buffer, "raw") else sys.stdout.buffer
    world = os.getppid()
    while True:
        try:
            ready, _, _ = select.select([fd], [], [], 1.0)
            data = os.read(fd, 1 << 16) if ready else b""
        except BlockingIOError:
            continue
        except OSError:  # no host has the port open (EIO), or the pty is gone
            if os.getppid() != world:
                return
            time.sleep(0.02)
            continue
        if not data:
            if os.getppid() != world:  # the world died
                return
            continue
        try:
            out.write(HEADER.pack(time.monotonic(), len(data)) + data)
        except BrokenPipeError:
            return


if __name__ == "__main__":
    main(int(sys.argv[1]))
