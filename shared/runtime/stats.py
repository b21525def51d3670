"""A node's counters: message rates per key, errors, rejections by reason."""

from __future__ import annotations

import collections
import threading

RATE_WINDOW_S = 5.0


class RateMeter:
    """Message rate over the last few seconds, counted in quarter-second buckets (a tick is a few
    integer operations: it runs for every message sent and received). Ticked from transport threads
    and read from the health timer: one lock keeps the buckets consistent."""

    BUCKETS_PER_S = 4

    def __init__(self) -> None:
        self.count = 0
        self._n = int(RATE_WINDOW_S * self.BUCKETS_PER_S)
        self._counts = [0] * self._n
        self._bucket = -1  # index of the newest bucket, in quarter seconds since the clock's epoch
        self._slot = 0  # its place in _counts
        self._first = 0.0  # time of the first tick: a young meter's window is shorter
        self._lock = threading.Lock()

    def tick(self, now: float) -> None:
        b = int(now * self.BUCKETS_PER_S)
        with self._lock:
            if b == self._bucket:  # most ticks: the bucket of the one before
                self.count += 1
                self._counts[self._slot] += 1
                return
            if b > self._bucket:
                self._roll(b)
            if not self.count:
                self._first = now
            self.count += 1
            if b > self._bucket - self._n:  # a tick stamped before the window (another thread) counts only in total
                self._counts[b % self._n] += 1

    def _roll(self, b: int) -> None:
        for i in range(max(self._bucket + 1, b - self._n + 1), b + 1):  # buckets passed since: empty
            self._counts[i % self._n] = 0
        self._bucket = b
        self._slot = b % self._n

    def rate(self, now: float) -> float:
        with self._lock:
            b = int(now * self.BUCKETS_PER_S)
            if b > self._bucket:
                self._roll(b)
            n, first = sum(self._counts), self._first
        covered = (self._n - 1 + now * self.BUCKETS_PER_S - b) / self.BUCKETS_PER_S  # full buckets and the current part
        span = min(now - first, covered) if self.count else 0.0
        if n < 2 or span <= 0:
            return 0.0
        return (n - 1) / span if span < RATE_WINDOW_S * 0.5 else n / span


class Stats:
    """Counters of one node, counted from the loop and from inline handlers' Zenoh threads."""

    def __init__(self) -> None:
        self.published: dict[str, RateMeter] = {}
        self.received: dict[str, RateMeter] = {}
        self.errors: collections.Counter[str] = collections.Counter()
        self.rejected: dict[str, collections.Counter[str]] = {}  # key -> reason -> count
        self._lock = threading.Lock()

    def reject(self, key: str, reason: str) -> None:
        with self._lock:
            self.rejected.setdefault(key, collections.Counter())[reason] += 1
        self.count(reason, key)

    def count(self, name: str, key: str | None = None, n: int = 1) -> None:
        with self._lock:
            self.errors[name if key is None else f"{name}:{key}"] += n

    def received_meter(self, key: str) -> RateMeter:
        with self._lock:
            return self.received.setdefault(key, RateMeter())

    def snapshot(self) -> tuple[dict, dict, dict, dict]:
        """(published, received meters, errors, rejected) copied at one moment: inline handlers add
        keys from Zenoh threads while the health report is built."""
        with self._lock:
            return (dict(self.published), dict(self.received), dict(self.errors),
                    {k: dict(c) for k, c in self.rejected.items()})
