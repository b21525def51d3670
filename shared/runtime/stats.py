"""A node's counters: message rates per key, errors, rejections by reason."""

from __future__ import annotations

import collections
import itertools
import threading

RATE_WINDOW_S = 5.0


class Tally:
    """A count bumped from several threads without a lock, for once-per-message counts: ``add()`` is
    one call of C code (``itertools.count``), which the GIL runs whole."""

    __slots__ = ("_count", "add")

    def __init__(self) -> None:
        self._count = itertools.count()
        self.add = self._count.__next__

    @property
    def value(self) -> int:
        return int(repr(self._count)[6:-1])  # "count(n)": itertools.count shows its next value only so


class RateMeter:
    """Message rate over the last few seconds, in quarter-second buckets. A tick is a lock-free
    count (``Tally``) and one comparison; the first tick of a new bucket notes, under a lock, the
    count at which the bucket began, so the ticks in a window are a difference of two counts.
    Ticked from transport threads and read from the health timer."""

    BUCKETS_PER_S = 4

    def __init__(self) -> None:
        self._ticks = Tally()
        self._add = self._ticks.add
        self._n = int(RATE_WINDOW_S * self.BUCKETS_PER_S)
        self._starts = [0] * self._n  # per bucket of the window (ring): the count when it began
        self._bucket = -1  # the newest bucket, in quarter seconds since the clock's epoch
        self._edge = float("-inf")  # when the newest bucket ends: a tick from then on rolls
        self._first = 0.0  # time of the first tick: a young meter's window is shorter
        self._lock = threading.Lock()

    @property
    def count(self) -> int:
        return self._ticks.value

    def tick(self, now: float) -> None:
        if now >= self._edge:
            self._roll(now)
        self._add()

    def _roll(self, now: float) -> None:
        with self._lock:
            b = int(now * self.BUCKETS_PER_S)
            if b <= self._bucket:  # another thread rolled meanwhile
                return
            if self._bucket < 0:
                self._first = now
            self._mark(b)

    def _mark(self, b: int) -> None:
        """Buckets from the newest to ``b`` begin at the count so far (those passed saw no tick)."""
        count = self._ticks.value
        for i in range(max(self._bucket + 1, b - self._n + 1), b + 1):
            self._starts[i % self._n] = count
        self._bucket = b
        self._edge = (b + 1) / self.BUCKETS_PER_S

    def rate(self, now: float) -> float:
        with self._lock:
            if self._bucket < 0:  # never ticked
                return 0.0
            b = int(now * self.BUCKETS_PER_S)
            if b > self._bucket:
                self._mark(b)
            count, first = self._ticks.value, self._first
            n = count - self._starts[(b + 1) % self._n]  # ticks since the oldest bucket of the window began
        covered = (self._n - 1 + now * self.BUCKETS_PER_S - b) / self.BUCKETS_PER_S  # full buckets and the current part
        span = min(now - first, covered)
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
