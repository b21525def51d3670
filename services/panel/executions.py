"""Executions run from the dashboard and their logged outcomes (no viser; Zenoh only through the
``query`` callable it is given).

One execution: the world is reset to a layout (``@cmd/reset {"seed"}``: the layout of that seed's
first demonstration), switched to robot mode (the teacher's hands leave, the objects are physical),
the served policy drives the armed robot for ``seconds``, then the world's success test answers
(``@cmd/outcome``: success and its distances, e.g. the connector gap) and the world returns to
teacher mode. STOP ends the wait early; the outcome is still measured and logged as stopped. Each
outcome is one JSON line in ``executions.jsonl`` beside the served checkpoint, so the model list
shows a model's executions, with the teaching session, task and teacher it ran in.
"""

from __future__ import annotations

import json
import math
import os
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

WORLD = "xm/world/sim/@cmd"
LOG_NAME = "executions.jsonl"
MAX_SECONDS = 120.0
ARMED_POLL_S = 0.1  # how often a running execution reads the arm state


class ExecutionError(ValueError):
    """An execution refused or broken off; the message says why."""


@dataclass
class Execution:
    """One logged execution."""
    checkpoint: str  # the served checkpoint ("" with the naive fallback)
    method: str  # the policy's method while it ran (learned, naive, ...)
    seed: int  # the world's layout seed
    seconds: float  # how long the robot ran (shorter when stopped)
    success: bool
    distances: dict[str, float] = field(default_factory=dict)  # the success test's measurements (mm)
    checks: dict[str, bool] = field(default_factory=dict)  # its yes/no measurements (seated, checked, ...)
    stopped: bool = False
    task: str = ""
    session: str | None = None  # the teaching session it ran in
    teacher: str = ""
    time: str = ""  # local date and time it ended

    def to_json(self) -> str:
        return json.dumps(asdict(self))


def outcome_fields(reply: dict) -> tuple[bool, dict[str, float], dict[str, bool]]:
    """(success, distances, checks) from the world's ``@cmd/outcome`` reply; ExecutionError for a
    reply without a boolean ``success``."""
    if not isinstance(reply, dict) or not reply.get("ok") or not isinstance(reply.get("success"), bool):
        why = reply.get("error") if isinstance(reply, dict) and reply.get("error") else f"{reply!r}"[:200]
        raise ExecutionError(f"the world's success test did not answer: {why}")
    skip = {"ok", "success", "task", "mode", "sim_time"}
    checks = {k: v for k, v in reply.items() if k not in skip and isinstance(v, bool)}
    distances = {k: round(float(v), 2) for k, v in reply.items()
                 if k not in skip and isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)}
    return reply["success"], distances, checks


class Runner:
    """Runs one execution at a time. ``query(key, request)`` returns the JSON replies of one Zenoh
    query ([] when nobody answered)."""

    def __init__(self, query: Callable[[str, dict], list[dict]]) -> None:
        self.query = query
        self.stop = threading.Event()  # set by STOP: the running execution ends now
        self._lock = threading.Lock()
        self.started: float | None = None  # wall time the running execution started

    @property
    def running(self) -> bool:
        return self._lock.locked()

    def _wait(self, seconds: float, armed_now: Callable[[], bool | None] | None) -> bool:
        """Wait ``seconds``; True when STOP or the robot reading disarmed ended the wait early."""
        deadline = time.monotonic() + seconds
        while (left := deadline - time.monotonic()) > 0:
            if self.stop.wait(min(left, ARMED_POLL_S)) or (armed_now is not None and armed_now() is False):
                return True
        return False

    def _ask(self, verb: str, request: dict) -> dict:
        replies = self.query(f"{WORLD}/{verb}", request)
        if not replies:
            raise ExecutionError(f"the world did not answer @cmd/{verb} (executions need the simulated workcell)")
        if not replies[0].get("ok"):
            raise ExecutionError(f"the world refused @cmd/{verb}: {replies[0].get('error', replies[0])}")
        return replies[0]

    def run(self, seed: int, seconds: float, armed: bool | None, serving: str | None, method: str,
            context: dict | None = None, on_started: Callable[[], None] | None = None,
            armed_now: Callable[[], bool | None] | None = None) -> Execution:
        """Reset, robot mode, wait, outcome, teacher mode; ExecutionError when refused (robot not
        armed, another execution running, a bad request) or when the world does not answer.
        ``armed_now()``: the robot's arm state; the execution ends when it reads disarmed (every STOP and
        disarm disarms it, so they end it whatever order viser's worker threads ran the presses in,
        even one handled before this execution cleared ``stop``)."""
        if not 0 < seconds <= MAX_SECONDS:
            raise ExecutionError(f"seconds must be in (0, {MAX_SECONDS:g}], got {seconds}")
        if armed is not True:
            raise ExecutionError("the robot is not armed: arm it first (the robot never moves unless armed)"
                                 if armed is False else "the robot service does not answer")
        if not self._lock.acquire(blocking=False):
            raise ExecutionError(f"an execution is running (started "
                                 f"{time.strftime('%H:%M:%S', time.localtime(self.started or 0))}); wait or STOP it")
        try:
            self.started = time.time()
            self.stop.clear()
            self._ask("reset", {"seed": int(seed)})
            self._ask("mode", {"mode": "robot"})
            t0 = time.monotonic()
            if on_started is not None:
                on_started()
            stopped = self._wait(seconds, armed_now)
            ran = time.monotonic() - t0
            try:
                reply = self.query(f"{WORLD}/outcome", {})
                success, distances, checks = outcome_fields(reply[0] if reply else {"error": "no answer"})
            finally:
                self._ask("mode", {"mode": "teacher"})
            ctx = context or {}
            return Execution(checkpoint=serving or "", method=method, seed=int(seed), seconds=round(ran, 2),
                             success=success and not stopped, distances=distances, checks=checks, stopped=stopped,
                             task=str(reply[0].get("task", "")), session=ctx.get("session"),
                             teacher=str(ctx.get("teacher", "")), time=time.strftime("%Y-%m-%d %H:%M:%S"))
        finally:
            self.started = None
            self._lock.release()


def log_path(checkpoint: str | Path) -> Path:
    """The execution log of a checkpoint: beside it."""
    return Path(checkpoint).parent / LOG_NAME


def append(path: Path, execution: Execution) -> None:
    """One line appended and flushed to disk (a reader sees whole lines or nothing new)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("a") as f:
        f.write(execution.to_json() + "\n")
        f.flush()
        os.fsync(f.fileno())


def read(path: Path) -> tuple[list[Execution], int]:
    """The executions logged in ``path`` and how many of its lines were not readable (skipped)."""
    try:
        lines = path.read_text().splitlines()
    except OSError:
        return [], 0
    out, bad = [], 0
    for line in lines:
        if not line.strip():
            continue
        try:
            out.append(Execution(**json.loads(line)))
        except (ValueError, TypeError):
            bad += 1
    return out, bad


def summary(executions: list[Execution]) -> str:
    """``2 / 3 succeeded`` plus the last one's distances, or ``-``."""
    if not executions:
        return "-"
    ok = sum(e.success for e in executions)
    return f"{ok} / {len(executions)} succeeded"


def describe(e: Execution) -> str:
    """One execution as a line of the Execute folder."""
    verdict = "**success**" if e.success else ("stopped" if e.stopped else "**failure**")
    dist = ", ".join(f"{k.removesuffix('_mm').replace('_', ' ')} {v:g} mm" for k, v in e.distances.items()
                     if k.endswith("_mm"))
    model = Path(e.checkpoint).parent.name if e.checkpoint else e.method
    return (f"{e.time[11:]} `{model}` layout {e.seed}: {verdict} after {e.seconds:.1f} s"
            + (f" ({dist})" if dist else ""))
