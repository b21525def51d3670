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
