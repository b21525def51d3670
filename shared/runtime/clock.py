"""Time base of a deployment: wall time, or simulated time published by the world on xm/clock.

Time may jump back: the world restarts at 0 (a new process, ``@cmd/reset``), a recording is
replayed in a loop, or the host's wall clock is stepped. The clock notices a step back of more
than ``JUMP_BACK_S``, counts it (``jumps``), wakes every sleeper and tells its listeners;
``ticks()`` then rebases its schedule on the new timeline instead of waiting for the old one.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable

JUMP_BACK_S = 1.0  # a smaller step back is jitter (e.g. stamps of two publishers), not a restart


class Clock:
    """``now()`` in seconds. In sim mode time only advances when ``xm/clock`` arrives."""

    def __init__(self, mode: str = "wall") -> None:
        if mode not in ("wall", "sim"):
            raise ValueError(f"clock mode must be 'wall' or 'sim', got {mode!r}")
        self.mode = mode
        self.jumps = 0  # times the clock went back by more than JUMP_BACK_S
        self._sim_time: float | None = None
        self._observed: float | None = None  # the newest xm/clock sample, set on Zenoh's thread
        self._advance_scheduled = False
        self._last_wall: float | None = None
        self._waiters: list[tuple[float, asyncio.Future]] = []
        self._listeners: list[Callable[[float, float], None]] = []

    @property
    def started(self) -> bool:
        return self.mode == "wall" or self._sim_time is not None

    def on_jump(self, listener: Callable[[float, float], None]) -> None:
        """``listener(old, new)`` runs (on the event loop) each time the clock jumps back."""
        self._listeners.append(listener)

    def now(self) -> float:
        if self.mode == "wall":
            t = time.time()
            if self._last_wall is not None and t < self._last_wall - JUMP_BACK_S:
                self._jumped(self._last_wall, t)
            self._last_wall = t
            return t
        return self._sim_time if self._sim_time is not None else 0.0

    def reference(self) -> float | None:
        """The time a message's stamp is checked against (None: the clock has not started): the
        newest clock sample received, even while the event loop is too busy to ``advance``, so a
        receiver that is behind does not refuse fresh messages as stamped in the future."""
        if self.mode == "wall":
            return self.now()
        return self._observed if self._observed is not None else self._sim_time

    def observe(self, sim_time: float, loop: asyncio.AbstractEventLoop) -> None:
        """Zenoh's thread, for each xm/clock sample: the newest time at once, then ``advance`` on the
        loop (samples that arrive before it runs coalesce into the newest)."""
        self._observed = sim_time
        if not self._advance_scheduled:
            self._advance_scheduled = True
            loop.call_soon_threadsafe(self._advance_observed)

    def _advance_observed(self) -> None:
        self._advance_scheduled = False  # before reading: a sample observed from here on schedules again
        if self._observed is not None:
            self.advance(self._observed)

    def advance(self, sim_time: float) -> None:
        """Called by the runtime for each xm/clock message (on the event loop)."""
        previous = self._sim_time
        self._sim_time = sim_time
        if previous is not None and sim_time < previous - JUMP_BACK_S:
            self._jumped(previous, sim_time)
        ready = [w for w in self._waiters if w[0] <= sim_time]
        if ready:
            self._waiters = [w for w in self._waiters if w[0] > sim_time]
            for _, fut in ready:
                if not fut.done():
                    fut.set_result(None)

    def _jumped(self, old: float, new: float) -> None:
        self.jumps += 1
        # Release everybody rather than let them wait for a time long gone.
        for _, fut in self._waiters:
            if not fut.done():
                fut.set_result(None)
        self._waiters.clear()
        for listener in self._listeners:
            listener(old, new)

    async def sleep_until(self, t: float) -> None:
        """Returns at ``t``, or early when the clock jumps back meanwhile (check ``now()``)."""
        if self.mode == "wall":
            await asyncio.sleep(max(0.0, t - time.time()))
            return
        if self._sim_time is not None and self._sim_time >= t:
            return
        fut = asyncio.get_running_loop().create_future()
        self._waiters.append((t, fut))
        await fut

    async def ticks(self, hz: float):
        """Yield the tick times of a fixed-rate loop; skips missed ticks instead of bursting, and
        restarts the schedule from the present when the clock jumps back."""
        period = 1.0 / hz
        while not self.started:
            await asyncio.sleep(0.01)
        t_next = self.now()
        jumps = self.jumps
        while True:
            now = self.now()  # notices a wall clock stepped back
            if self.jumps != jumps:
                jumps, t_next = self.jumps, now
            await self.sleep_until(t_next)
            if self.jumps != jumps:
                continue  # woken by a jump: rebase above
            yield t_next
            t_next += period
            now = self.now()
            if t_next < now - period:
                t_next = now
