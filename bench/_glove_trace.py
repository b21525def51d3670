"""The glove service as deployed, with a timestamp per frame at each stage, for bench/glove.py.

Usage: ``python bench/_glove_trace.py OUT.npz --deployment D --instance H``. Runs
``services.glove`` unchanged except that the reader thread notes, per frame, when its read returned
the bytes, when decoding and calibration were done and when the publish call returned
(``time.perf_counter``, CLOCK_MONOTONIC: comparable across processes); at exit it writes them with
the priorities the service got. Costs one list append per frame.
"""

from __future__ import annotations

import atexit
import json
import os
import sys
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # runnable as a script from anywhere

from services.glove.driver import GloveDriver  # noqa: E402
from services.glove.service import GloveService  # noqa: E402
from shared.realtime import TtyWorkers  # noqa: E402
from shared.runtime import service_main  # noqa: E402

_records: list[tuple[int, float, float, float]] = []  # (sequence, read returned, decoded, published)
_read_at = threading.local()
_services: list[GloveService] = []
_raised_at: list[tuple[float, int]] = []  # (time, kernel tty workers raised then), after the first look
_on_bytes, _on_frame, _init = GloveDriver._on_bytes, GloveService._on_frame, GloveService.__init__
_raise_new = TtyWorkers.raise_new


def _traced_bytes(self: GloveDriver, data: bytes) -> None:
    _read_at.t = time.perf_counter()
    _on_bytes(self, data)


def _traced_frame(self: GloveService, frame, pressure: np.ndarray, stamp: float) -> None:
    decoded = time.perf_counter()
    _on_frame(self, frame, pressure, stamp)
    _records.append((frame.sequence, getattr(_read_at, "t", np.nan), decoded, time.perf_counter()))


def _traced_raise_new(self: TtyWorkers) -> int:
    first = not self.seen
    raised = _raise_new(self)
    if raised and not first:
        _raised_at.append((time.perf_counter(), raised))
    return raised


def _traced_init(self: GloveService, *args, **kwargs) -> None:
    _init(self, *args, **kwargs)
    _services.append(self)


def _policies() -> dict[str, int]:
    """How many of the process's threads run under each scheduling policy."""
    names = {os.SCHED_OTHER: "normal", os.SCHED_FIFO: "fifo", os.SCHED_RR: "rr"}
    out: dict[str, int] = {}
    for tid in os.listdir("/proc/self/task"):
        try:
            name = names.get(os.sched_getscheduler(int(tid)), "other")
        except OSError:
            continue
        out[name] = out.get(name, 0) + 1
    return out


def _dump(path: str, at_start: dict) -> None:
    svc = _services[0] if _services else None
    info = {"reader_priority": svc.driver.link.priority if svc else "not started",
            "tty_workers_raised": svc.driver.tty_workers_raised if svc else 0,
            "tty_workers_raised_later_at": _raised_at,
            "thread_policies_running": at_start.get("policies", {})}
    np.savez(path, stages=np.array(_records, dtype=float).reshape(-1, 4), info=json.dumps(info))


def main() -> None:
    out = sys.argv.pop(1)
    GloveDriver._on_bytes = _traced_bytes
    GloveService._on_frame = _traced_frame
    GloveService.__init__ = _traced_init
    TtyWorkers.raise_new = _traced_raise_new
    at_start: dict = {}
    _first = GloveService._on_frame

    def note_policies_once(self: GloveService, *args) -> None:  # the threads as they are while frames flow
        if not at_start:
            at_start["policies"] = _policies()
        _first(self, *args)

    GloveService._on_frame = note_policies_once
    atexit.register(_dump, out, at_start)
    service_main("glove", GloveService)


if __name__ == "__main__":
    main()
