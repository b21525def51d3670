"""The recorder spare's buffer of the last seconds of messages, and its hand-over rules (no I/O here).

A standby spare of the recorder (services/recorder/spare.py) appends each message it receives to a
``SpareBuffer``: ``(key, payload, receive time ns)``, the oldest dropped first beyond ``seconds`` or
``max_bytes``. When the spare takes over a recording the killed recorder left, ``after_cut`` picks
the buffered messages that recording lacks: per key, those after the last message of the key the
killed recorder kept (found by payload, near its receive time), else those received after the
recording's cut time. ``Overlap`` then recognises, by key and payload and in order, the messages the
new recording's live subscription brings that the buffer already supplied.
"""

from __future__ import annotations

import collections
import threading
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

Entry = tuple[str, bytes, int]  # key, payload, receive time (ns since the epoch)

ENTRY_OVERHEAD = 120  # bytes an entry costs besides its payload and key (tuple, bytes and str objects)
MATCH_WINDOW_NS = 1_000_000_000  # two processes' receive times of one message lie closer than this


class SpareBuffer:
    """A ring of the last ``seconds`` of entries, at most ``max_bytes``; ``add`` is called from
    Zenoh's thread, the rest from anywhere."""

    def __init__(self, seconds: float = 3.0, max_bytes: int = 64 << 20) -> None:
        self.window_ns = int(seconds * 1e9)
        self.max_bytes = max_bytes
        self.bytes = 0
        self.dropped = 0  # entries dropped as too old or over the byte cap
        self.frozen = False
        self._entries: collections.deque[Entry] = collections.deque()
        self._lock = threading.Lock()

    def add(self, key: str, payload: bytes, t_ns: int) -> None:
        entries = self._entries
        with self._lock:
            if self.frozen:
                return
            entries.append((key, payload, t_ns))
            self.bytes += len(payload) + len(key) + ENTRY_OVERHEAD
            horizon = t_ns - self.window_ns
            while entries and (self.bytes > self.max_bytes or entries[0][2] < horizon):
                old_key, old_payload, _ = entries.popleft()
                self.bytes -= len(old_payload) + len(old_key) + ENTRY_OVERHEAD
                self.dropped += 1

    def since(self, t_ns: int) -> list[Entry]:
        """The entries received at or after ``t_ns``, oldest first."""
        with self._lock:
            out = []
            for entry in reversed(self._entries):
                if entry[2] < t_ns:
                    break
                out.append(entry)
        out.reverse()
        return out

    def freeze(self) -> list[Entry]:
        """Stop taking entries; returns all held, oldest first."""
        with self._lock:
            self.frozen = True
            return list(self._entries)

    def __len__(self) -> int:
        return len(self._entries)

    def span_s(self) -> float:
        """Seconds between the oldest and the newest entry held."""
        with self._lock:
            return (self._entries[-1][2] - self._entries[0][2]) * 1e-9 if len(self._entries) > 1 else 0.0


@dataclass(frozen=True)
class Cut:
    """Where a killed recorder's recording ends: the receive time of the last message it kept, and
    per key of its last chunk, the last payload it kept with that message's receive time."""

    time_ns: int
    last: dict[str, tuple[bytes, int]] = field(default_factory=dict)


def after_cut(entries: list[Entry], cut: Cut, takes: Callable[[str], bool]) -> list[Entry]:
    """The entries the recording lacks after ``cut``, of the keys ``takes`` accepts, in buffer order."""
    by_key: dict[str, list[int]] = {}
    for i, (key, _, _) in enumerate(entries):
        if key in by_key:
            by_key[key].append(i)
        elif takes(key):
            by_key[key] = [i]
    keep: list[int] = []
    for key, idx in by_key.items():
        start = None
        if key in cut.last:
            payload, t_last = cut.last[key]
            best = MATCH_WINDOW_NS + 1
            for j, i in enumerate(idx):
                _, p, t = entries[i]
                if abs(t - t_last) < best and p == payload:
                    start, best = j + 1, abs(t - t_last)
        if start is None:  # the key's last kept message is not in the buffer: by time
            start = next((j for j, i in enumerate(idx) if entries[i][2] > cut.time_ns), len(idx))
        keep += idx[start:]
    keep.sort()
    return [entries[i] for i in keep]


def overlaps(buffered: Iterable[Entry], live: Iterable[Entry]) -> bool:
    """True when a live message is one the buffer holds too (same key and payload)."""
    held = {(key, payload) for key, payload, _ in buffered}
    return bool(held) and any((key, payload) in held for key, payload, _ in live)


class Overlap:
    """The live copies of messages written from the buffer: per key, the buffered payloads received
    from ``live_from_ns`` on (the live subscription may have them too), and for a key ``replays``
    accepts (a state, whose subscription starts with its publisher's latest message) the last one
    written. ``is_copy`` consumes them in order."""

    def __init__(self, written: list[Entry], live_from_ns: int, replays: Callable[[str], bool]) -> None:
        self.expect: dict[str, collections.deque[bytes]] = {}
        last: dict[str, bytes] = {}
        for key, payload, t in written:
            last[key] = payload
            if t >= live_from_ns:
                self.expect.setdefault(key, collections.deque()).append(payload)
        for key, payload in last.items():
            if key not in self.expect and replays(key):
                self.expect[key] = collections.deque([payload])

    def is_copy(self, key: str, payload: bytes) -> bool:
        expected = self.expect.get(key)
        if not expected:
            return False
        if payload in expected:  # the live subscription may have started after the first ones
            while expected.popleft() != payload:
                pass
            if not expected:
                del self.expect[key]
            return True
        del self.expect[key]  # the live stream of this key goes on past what the buffer held
        return False

    def __bool__(self) -> bool:
        return bool(self.expect)
