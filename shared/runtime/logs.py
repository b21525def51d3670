"""Structured logging: one line per event, ``key=value`` fields, or JSON lines with XM_LOG_JSON=1."""

from __future__ import annotations

import json
import logging
import os
import sys
import time


class _Formatter(logging.Formatter):
    def __init__(self, name: str, as_json: bool) -> None:
        super().__init__()
        self.source = name
        self.as_json = as_json

    def format(self, record: logging.LogRecord) -> str:
        fields = getattr(record, "fields", {}) or {}
        if self.as_json:
            return json.dumps({"t": record.created, "level": record.levelname, "src": self.source,
                               "msg": record.getMessage(), **fields}, default=str)
        stamp = time.strftime("%H:%M:%S", time.localtime(record.created)) + f".{int(record.msecs):03d}"
        extra = "".join(f" {k}={v}" for k, v in fields.items())
        text = f"{stamp} {record.levelname:<5} {self.source}: {record.getMessage()}{extra}"
        if record.exc_info:
            text += "\n" + self.formatException(record.exc_info)
        return text


def setup_logging(source: str, level: str | None = None) -> logging.Logger:
    logger = logging.getLogger("xm")
    logger.handlers.clear()
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(_Formatter(source, os.environ.get("XM_LOG_JSON") == "1"))
    logger.addHandler(handler)
    logger.setLevel(level or os.environ.get("XM_LOG_LEVEL", "INFO"))
    logger.propagate = False
    return logger


def fields(**kw: object) -> dict:
    """``log.info("msg", extra=fields(a=1))`` attaches structured fields."""
    return {"fields": kw}


class RateLimitedLog:
    """One log line per kind of event, then a summary every ``every_s`` seconds while it recurs.

    ``warning(kind, msg, **fields)`` logs the first event of a kind at once; the next ones within
    ``every_s`` are only counted, and ``flush()`` (or the next event after the interval) writes
    "<msg> (n more in the last Ts)" with the latest fields. A flood of bad input costs a line per
    kind per interval, not a line per message.
    """

    def __init__(self, log: logging.Logger, every_s: float = 10.0) -> None:
        self.log = log
        self.every_s = every_s
        self._kinds: dict[str, list] = {}  # kind -> [last line time, suppressed count, level, msg, fields]

    def warning(self, kind: str, msg: str, **kw: object) -> None:
        self.emit(logging.WARNING, kind, msg, **kw)

    def emit(self, level: int, kind: str, msg: str, exc_info: BaseException | None = None, **kw: object) -> None:
        """``exc_info``: a traceback for the first line of the kind (the summaries only count)."""
        now = time.monotonic()
        entry = self._kinds.get(kind)
        if entry is None:
            self._kinds[kind] = [now, 0, level, msg, kw]
            self.log.log(level, msg, extra=fields(**kw), exc_info=exc_info)
            return
        entry[1] += 1
        entry[2:] = [level, msg, kw]
        if now - entry[0] >= self.every_s:
            self._summary(entry, now)

    def flush(self) -> None:
        """Writes the summaries that are due; call it every few seconds."""
        now = time.monotonic()
        for entry in self._kinds.values():
            if entry[1] and now - entry[0] >= self.every_s:
                self._summary(entry, now)

    def _summary(self, entry: list, now: float) -> None:
        last, count, level, msg, kw = entry
        self.log.log(level, f"{msg} ({count} more in the last {now - last:.0f} s)",
                     extra=fields(**kw))
        entry[0], entry[1] = now, 0
