"""A recording as a sequence of MCAP segments of ``segment_s`` seconds each.

The first segment has the requested name, ``NAME.mcap``; the next ones ``NAME.seg0001.mcap``,
``NAME.seg0002.mcap``, ... (shared/recording_files.py). A segment is closed (summary section and
footer written, fsync'ed) before the next one opens, so a crash leaves every closed segment
complete, readable by seeking readers, and only the open one cut (up to its last flushed chunk,
services/recorder/writer.py). ``repair_cut_segments`` turns such a cut segment, once no recorder
holds it, into a complete file in place; the recorder service runs it over its directory at start.
"""

from __future__ import annotations

import ctypes
import logging
import os
import time
from collections import Counter
from pathlib import Path
from typing import Any

from services.recorder.writer import (
    CHUNK_BYTES,
    FLUSH_S,
    McapRecorder,
    RecordingError,
    Summary,
    check_mcap,
    is_being_written,
    is_complete,
    repair,
)
from shared.recording_files import recording_segments, segment_key, segment_path

SEGMENT_S = 60.0
log = logging.getLogger("xm")


class SegmentedRecorder:
    """``McapRecorder``'s interface over a recording split into segments (``segment_s`` <= 0: one file)."""

    def __init__(self, path: str | Path, metadata: dict[str, Any] | None = None, segment_s: float = SEGMENT_S,
                 flush_s: float = FLUSH_S, chunk_bytes: int = CHUNK_BYTES, validate: bool = True,
                 first_index: int = 0) -> None:
        self.path = Path(path)
        if not self.path.name.endswith(".mcap"):
            raise RecordingError(f"{self.path}: a recording's file name ends in .mcap")
        self.segment_s = segment_s
        self.metadata = dict(metadata or {})
        self._options = {"flush_s": flush_s, "chunk_bytes": chunk_bytes, "validate": validate}
        self.segments: list[Path] = []
        self.counts: Counter[str] = Counter()
        self.span_ns: dict[str, list[int]] = {}
        self._done = {"bytes": 0, "chunks": 0, "durable": 0}  # of closed segments
        self.started = time.monotonic()
        self.closed = False
        self._summary: Summary | None = None
        self._index = first_index  # > 0: a recording resumed after a crash goes on in its next segment
        self._open(first_index, time.monotonic())

    def _open(self, index: int, now: float) -> None:
        path = segment_path(self.path, index)
        if index and path.exists():
            raise FileExistsError(f"{path} exists (segment {index} of {self.path}); recordings are never overwritten")
        meta = {**self.metadata, "recording": self.path.name, "segment": str(index),
                "segment_s": str(self.segment_s)}
        self.current = McapRecorder(path, meta, **self._options)
        self.segments.append(path)
        self._index = index
        self._opened = now

    @property
    def flush_s(self) -> float:
        return self.current.flush_s

    def write(self, key: str, msgtype: str, payload: bytes, log_time_ns: int | None = None) -> None:
        if self.closed:
            raise RecordingError(f"{self.path}: recording already closed")
        if self.segment_s > 0:
            self.maybe_rotate()
        log_time = log_time_ns if log_time_ns is not None else time.time_ns()
        self.current.write(key, msgtype, payload, log_time)
        self.counts[key] += 1
        span = self.span_ns.get(key)
        if span is None:
            self.span_ns[key] = [log_time, log_time]
        else:
            span[1] = log_time

    def maybe_rotate(self, now: float | None = None) -> bool:
        """Close the open segment and start the next when it is ``segment_s`` old."""
        now = time.monotonic() if now is None else now
        if self.closed or self.segment_s <= 0 or now - self._opened < self.segment_s:
            return False
        done = self.current.close()
        self._done["bytes"] += done.bytes
        self._done["chunks"] += done.chunks
        self._done["durable"] += done.durable
        self._open(self._index + 1, now)
        trim_heap()
        return True

    def maybe_flush(self, now: float | None = None) -> bool:
        """Rotate when due, flush the open segment when its chunk is ``flush_s`` old: call it from a timer."""
        rotated = self.maybe_rotate(now)
        return self.current.maybe_flush(now) or rotated

    def flush(self) -> None:
        self.current.flush()

    def rates(self) -> dict[str, float]:
        return {k: (self.counts[k] - 1) / ((b - a) * 1e-9) if b > a else 0.0 for k, (a, b) in self.span_ns.items()}

    def summary(self) -> Summary:
        cur = self.current.summary()
        return Summary(str(self.path), dict(self.counts), self._done["bytes"] + cur.bytes,
                       time.monotonic() - self.started, self._done["chunks"] + cur.chunks, self.rates(),
                       self._done["durable"] + cur.durable)

    def close(self) -> Summary:
        if not self.closed:
            self.current.close()
            self._done["bytes"] += self.current.bytes
            self._done["chunks"] += self.current.chunks
            self._done["durable"] += self.current.durable
            self.closed = True
            self._summary = Summary(str(self.path), dict(self.counts), self._done["bytes"],
                                    time.monotonic() - self.started, self._done["chunks"], self.rates(),
                                    self._done["durable"])
        return self._summary


_MALLOC_TRIM = getattr(ctypes.CDLL(None), "malloc_trim", None)  # glibc's; absent on musl and macOS


def trim_heap() -> bool:
    """Hand the heap's free pages back to the OS (glibc's ``malloc_trim``); False where there is none.

    A segment's chunk buffers and index are freed when it closes, but glibc keeps freed heap pages
    mapped, so without this the recorder's RSS steps up to the largest backlog it ever wrote."""
    if _MALLOC_TRIM is None:
        return False
    _MALLOC_TRIM(0)
    return True


def next_segment_index(path: str | Path) -> int:
    """The index the next segment of the recording whose first segment is ``path`` gets (0: none yet)."""
    existing = [segment_key(p)[1] for p in recording_segments(path) if p.exists()]
    return max(existing) + 1 if existing else 0


def repair_cut_segments(directory: str | Path) -> list[dict]:
    """Make every cut MCAP file (no footer) in ``directory`` that no live recorder holds complete, in
    place: the messages up to its last whole chunk are rewritten with a summary and footer (a crash
    leaves at most the open segment of each recording cut). Returns one report per file."""
    directory = Path(directory)
    reports: list[dict] = []
    if not directory.is_dir():
        return reports
    for path in sorted(directory.glob("*.mcap"), key=lambda p: (segment_key(p), p.name)):
        try:
            check_mcap(path)
            if is_complete(path) or is_being_written(path):
                continue
            tmp = path.with_name(path.name + ".repairing")
            n = repair(path, tmp)
            os.replace(tmp, path)
        except (RecordingError, OSError) as exc:
            reports.append({"path": str(path), "ok": False, "error": str(exc)})
            log.warning("cut recording segment not repaired", extra={"fields": {"path": str(path), "error": str(exc)}})
            continue
        reports.append({"path": str(path), "ok": True, "messages": n})
        log.warning("repaired a recording segment cut by a crash",
                    extra={"fields": {"path": str(path), "messages": n}})
    return reports
