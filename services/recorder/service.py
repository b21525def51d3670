"""recorder node: record keys to MCAP on command (`@cmd/start`, `@cmd/stop`, `@cmd/status`).

Subscriptions are lossless FIFOs of raw payloads; each key's type comes from the registry.
Keys under `@` (health, liveliness, commands) are never recorded; unknown keys are counted.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

from services.recorder.writer import McapRecorder
from shared import keys
from shared.runtime import Node, Subscription, fifo


class Recording:
    """One open recording: a subscription feeding a writer."""

    def __init__(self, node: Node, path: Path, pattern: str, metadata: dict[str, str]) -> None:
        self.node = node
        self.pattern = pattern
        self.writer = McapRecorder(path, metadata)
        self.started = time.monotonic()
        self.unknown: dict[str, int] = {}
        self.sub: Subscription = node.subscribe(pattern, self._on, fifo(), msgtype="raw")

    def _on(self, payload: bytes, key: str) -> None:
        if "/@" in key:
            return
        msgtype = keys.msgtype_of(key)
        if msgtype is None:
            self.unknown[key] = self.unknown.get(key, 0) + 1
            self.node.stats.count("unregistered_key", key)
            return
        self.writer.write(key, msgtype, payload)

    def summary(self) -> dict:
        return {"path": str(self.writer.path), "messages": dict(self.writer.counts), "bytes": self.writer.bytes,
                "seconds": round(time.monotonic() - self.started, 3), "unknown_keys": self.unknown}

    def stop(self) -> dict:
        self.sub.close()
        self.writer.close()
        return self.summary()


def default_path(directory: str | Path) -> Path:
    return Path(directory) / time.strftime("xm-%Y%m%d-%H%M%S.mcap")


class RecorderService:
    @dataclass
    class Params:
        directory: str = "recordings"

    def __init__(self, node: Node, params: Params) -> None:
        self.node = node
        self.p = params
        self.recording: Recording | None = None
        self.last: dict | None = None
        node.queryable("start", self.cmd_start)
        node.queryable("stop", self.cmd_stop)
        node.queryable("status", self.cmd_status)
        node.health_extra = lambda: {"recording": self.recording.summary() if self.recording else None}

    def cmd_start(self, req: dict) -> dict:
        if self.recording is not None:
            return {"ok": False, "error": f"already recording to {self.recording.writer.path}"}
        path = Path(req["path"]) if req.get("path") else default_path(self.p.directory)
        pattern = str(req.get("keys", "xm/**"))
        self.recording = Recording(self.node, path, pattern, {"keys": pattern, "started": time.ctime()})
        self.node.log.info("recording started", extra={"fields": {"path": str(path), "keys": pattern}})
        return {"ok": True, "path": str(path)}

    def cmd_stop(self, _req: dict) -> dict:
        if self.recording is None:
            return {"ok": False, "error": "not recording"}
        self.last = self.recording.stop()
        self.recording = None
        self.node.log.info("recording stopped", extra={"fields": {"path": self.last["path"]}})
        return {"ok": True, **self.last}

    def cmd_status(self, _req: dict) -> dict:
        return {"ok": True, "recording": self.recording.summary() if self.recording else None, "last": self.last}

    async def close(self) -> None:
        if self.recording is not None:
            self.recording.stop()
