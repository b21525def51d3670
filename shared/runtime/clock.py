"""Time base of a deployment: wall time, or simulated time published by the world on xm/clock."""

from __future__ import annotations

import asyncio
import time


class Clock:
    """``now()`` in seconds. In sim mode time only advances when ``xm/clock`` arrives."""

    def __init__(self, mode: str = "wall") -> None:
        if mode not in ("wall", "sim"):
            raise ValueError(f"clock mode must be 'wall' or 'sim', got {mode!r}")
        self.mode = mode
        self._sim_time: float | None = None
        self._waiters: list[tuple[float, asyncio.Future]] = []

    @property
    def started(self) -> bool:
        return self.mode == "wall" or self._sim_time is not None

    def now(self) -> float:
        if self.mode == "wall":
            return time.time()
        return self._sim_time if self._sim_time is not None else 0.0

    def advance(self, sim_time: float) -> None:
        """Called by the runtime for each xm/clock message (on the event loop)."""
        if self._sim_time is not None and sim_time < self._sim_time - 1.0:
            # The world restarted: release everybody rather than wait for a time long gone.
            for _, fut in self._waiters:
                if not fut.done():
                    fut.set_result(None)
            self._waiters.clear()
        self._sim_time = sim_time
        ready = [w for w in self._waiters if w[0] <= sim_time]
        if ready:
            self._waiters = [w for w in self._waiters if w[0] > sim_time]
            for _, fut in ready:
                if not fut.done():
                    fut.set_result(None)

    async def sleep_until(self, t: float) -> None:
        if self.mode == "wall":
            await asyncio.sleep(max(0.0, t - time.time()))
            return
        if self._sim_time is not None and self._sim_time >= t:
            return
        fut = asyncio.get_running_loop().create_future()
        self._waiters.append((t, fut))
        await fut

    async def ticks(self, hz: float):
        """Yield the tick times of a fixed-rate loop; skips missed ticks instead of bursting."""
        period = 1.0 / hz
        while not self.started:
            await asyncio.sleep(0.01)
        t_next = self.now()
        while True:
            await self.sleep_until(t_next)
            yield t_next
            t_next += period
            now = self.now()
            if t_next < now - period:
                t_next = now
