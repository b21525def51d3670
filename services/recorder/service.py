"""recorder node: record keys to MCAP on command (`@cmd/start`, `@cmd/stop`, `@cmd/status`).

A recording subscribes to raw payloads on Zenoh's thread, which only notes each sample's receive
time and queues it; the writer takes what arrived every ``DRAIN_S`` on the event loop (one loop
wake-up per batch, not one per message), bounded by ``MAX_PENDING`` waiting messages (more are
counted as ``queue_overflow``). Each key's type comes from the registry. Keys with an `@` chunk
(health, liveliness, commands) are never recorded; unregistered keys and payloads that do not
decode as their key's type are counted in @health and skipped. A recording
is written in segments of ``segment_s`` (services/recorder/segments.py); at start the service
repairs the segments in its directory that a crash left cut. A recording in progress is noted in
``<directory>/.recording-<instance>.json`` until it is stopped: a recorder that finds the note at
start (it was killed while recording) resumes that recording in its next segment at once, so a
crash of the recorder costs the recording only the recorder's own restart. A standby spare
(``--standby``) listens while it waits (services/recorder/spare.py): it keeps the last
``spare_buffer_s`` of the ``keys`` pattern, and when it takes over a recording in progress the
resumed segment starts with the buffered messages received after the cut one's last, then the
live stream without the copies of those; a kill of the recorder then costs the recording nothing
the buffer held (@health ``spare_buffer``).
"""

from __future__ import annotations

import asyncio
import collections
import json
import os
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import zenoh

from services.recorder.segments import SEGMENT_S, SegmentedRecorder, next_segment_index, repair_cut_segments
from services.recorder.spare import Handoff, SpareListener, recording_cut
from services.recorder.writer import RecordingError, warm_up
from shared import keys, msgs
from shared.config import load_deployment
from shared.keys import is_internal
from shared.runtime import Node, Subscription, fifo
from shared.runtime.logs import fields

DRAIN_S = 0.02  # the writer's period: at rig rates ~70 messages a batch, a few ms of work
MAX_PENDING = 100_000  # messages received and not yet written (~1.5 s of a rig's streams at most)
DROP_KINDS = ("unregistered_key", "bad_payload", "write_error", "queue_overflow")


def default_path(directory: str | Path, now: float | None = None) -> Path:
    """``<directory>/xm-YYYYmmdd-HHMMSS.mcap``, suffixed ``-2``, ``-3``... rather than overwrite."""
    stem = time.strftime("xm-%Y%m%d-%H%M%S", time.localtime(now))
    path = Path(directory) / f"{stem}.mcap"
    n = 2
    while path.exists():
        path = Path(directory) / f"{stem}-{n}.mcap"
        n += 1
    return path


def registered_types() -> list[str]:
    return sorted({spec.msgtype for spec in keys.REGISTRY} | set(keys.OPTIONAL.values()))


def check_pattern(pattern: str) -> str:
    try:
        zenoh.KeyExpr(pattern)
    except Exception as exc:
        raise ValueError(f"keys {pattern!r} is not a valid Zenoh key expression ({exc})") from None
    if not pattern.startswith("xm/") and pattern not in ("**", "xm/**"):
        raise ValueError(f"keys {pattern!r}: workcell keys start with xm/ (e.g. xm/** or xm/glove/*/tactile)")
    return pattern


class Recording:
    """One open recording: a lossless raw subscription queueing for a writer that drains and
    flushes on a timer."""

    def __init__(self, node: Node, path: Path, pattern: str, metadata: dict[str, Any],
                 segment_s: float = SEGMENT_S, first_index: int = 0, handoff: Handoff | None = None) -> None:
        self.node = node
        self.handoff = handoff  # a listening spare's takeover: its buffer is written before the live stream
        self.pattern = check_pattern(pattern)
        warm_up(registered_types())  # cached: costs only the first time in a process
        self.writer = SegmentedRecorder(path, {**metadata, "keys": pattern}, segment_s, first_index=first_index)
        self.unknown: Counter[str] = Counter()
        self.malformed: Counter[str] = Counter()
        self.write_errors = 0
        self.late = 0
        self.closed = False
        # (key, payload, receive time in ns): appended on Zenoh's thread, taken on the loop
        self._pending: collections.deque[tuple[str, bytes, int]] = collections.deque()
        self._types: dict[str, str | None] = {}  # key -> its type; "" internal, None unregistered
        # States (on_change outputs: the session label) come through subscriptions with history, so a
        # recording starts with each one's latest message; every other key through a plain one (Zenoh's
        # advanced subscriber, which history needs, lost a share of recon's messages under load).
        self._states = [spec.key for spec in keys.PATTERNS if spec.on_change and keys.key_matches(pattern, spec.key)]
        self._is_state: dict[str, bool] = {}  # key -> whether a state subscription brings it
        if handoff is not None:
            handoff.live_from(time.time_ns())
        try:
            self.subs: list[Subscription] = [node.subscribe(pattern, self._arrived_stream, fifo(), msgtype="raw",
                                                            inline=True)]
            self.subs += [node.subscribe(state, self._arrived_state, fifo(), msgtype="raw", inline=True,
                                         history=True) for state in self._states]
        except Exception:
            self.writer.close()
            path.unlink(missing_ok=True)
            raise
        self._drainer = node.spawn(self._drain_loop(), name="recorder-write")

    def _state_key(self, key: str) -> bool:
        state = self._is_state.get(key)
        if state is None:
            state = self._is_state[key] = any(keys.key_matches(s, key) for s in self._states)
        return state

    def _takes(self, key: str) -> bool:
        return not is_internal(key) and keys.key_matches(self.pattern, key)

    def _arrived_stream(self, payload: bytes, key: str) -> None:
        """Zenoh's thread: a stream's message (a state's comes through its own subscription)."""
        if not self._state_key(key):
            self._arrived(payload, key)

    def _arrived_state(self, payload: bytes, key: str) -> None:
        """Zenoh's thread: a state's message (about 1 Hz), recorded when the recording's pattern takes its key."""
        if keys.key_matches(self.pattern, key):
            self._arrived(payload, key)

    def _arrived(self, payload: bytes, key: str) -> None:
        """Zenoh's thread: stamp and queue, nothing else (a deque's append is atomic)."""
        if self.closed:
            self.late += 1
            return
        if len(self._pending) >= MAX_PENDING:
            self.node.stats.count("queue_overflow")
            return
        self._pending.append((key, payload, time.time_ns()))

    def _type(self, key: str) -> str | None:
        """The type a key is recorded as, looked up on its first message."""
        if is_internal(key):
            self._types[key] = ""
        else:
            self._types[key] = keys.msgtype_of(key)
            if self._types[key] is None:
                self.node.log.warning("key not in the registry: skipped", extra=fields(key=key))
        return self._types[key]

    def take_over(self, force: bool = False) -> bool:
        """A spare's takeover: once the live subscription is on, write the buffered messages the
        recording lacks; False while the live stream waits for that."""
        handoff = self.handoff
        if handoff is None or handoff.done:
            return True
        backlog = handoff.take(self._pending, self._takes, self._state_key, force)
        if backlog is None:
            return False
        handoff.written = self._write(collections.deque(backlog), copies=False)
        self.node.stats.count("spare_buffer_written", n=handoff.written)
        self.node.log.info("recording continued from the spare's buffer", extra=fields(**handoff.report()))
        return True

    def write_pending(self) -> None:
        """Write what arrived so far, in order of arrival."""
        if self.take_over():
            self._write(self._pending)

    def _write(self, pending: collections.deque[tuple[str, bytes, int]], copies: bool = True) -> int:
        """Write and take these messages; returns how many were written. ``copies``: skip the live
        copies of what a takeover wrote from the spare's buffer."""
        types, write, written = self._types, self.writer.write, 0
        handoff = self.handoff if copies and self.handoff is not None and self.handoff.overlap else None
        for _ in range(len(pending)):
            key, payload, t = pending.popleft()
            if handoff is not None and handoff.is_copy(key, payload):
                self.node.stats.count("spare_buffer_duplicate")
                continue
            msgtype = types[key] if key in types else self._type(key)
            if not msgtype:
                if msgtype is None:
                    self.unknown[key] += 1
                    self.node.stats.count("unregistered_key", key)
                continue
            try:
                write(key, msgtype, payload, t)
                written += 1
            except msgs.MessageError as exc:
                if not self.malformed[key]:
                    self.node.log.warning("malformed payload: skipped",
                                          extra=fields(key=key, error=str(exc)[:200]))
                self.malformed[key] += 1
                self.node.stats.count("bad_payload", key)
            except OSError as exc:  # disk full, removed directory: keep counting, say so in health
                self._write_failed(exc)
            except Exception as exc:  # a writer bug must not end the recording
                self.node.handler_failed(key, exc)
        return written

    def _write_failed(self, exc: OSError) -> None:
        self.write_errors += 1
        self.node.stats.count("write_error")
        self.node.set_status("error", f"cannot write {self.writer.path}: {exc}")

    async def _drain_loop(self) -> None:
        while True:
            await asyncio.sleep(DRAIN_S)
            self.write_pending()
            try:
                self.writer.maybe_flush()
            except OSError as exc:
                self._write_failed(exc)

    def summary(self) -> dict:
        return {**self.writer.summary().as_dict(), "keys": self.pattern, "unknown_keys": dict(self.unknown),
                "malformed": dict(self.malformed), "write_errors": self.write_errors,
                "segments": [str(p) for p in self.writer.segments], "segment_s": self.writer.segment_s}

    async def stop(self) -> dict:
        """Unsubscribe, write what is still queued, close the file."""
        for sub in self.subs:
            sub.close()
        self._drainer.cancel()
        await asyncio.sleep(0.01)  # callbacks already running on Zenoh's threads queue their sample
        self.closed = True  # from here arrivals are counted as late
        await asyncio.sleep(0.01)
        self.take_over(force=True)
        self.write_pending()
        self.writer.close()
        return self.summary()


class RecorderService:
    # Set by __main__ from --deployment: written into each recording's metadata.
    deployment: ClassVar[str] = ""
    # A standby spare's listener (``prepare``), taken by the service it becomes.
    _spare: ClassVar[SpareListener | None] = None

    @dataclass
    class Params:
        directory: str = "recordings"
        keys: str = "xm/**"  # default pattern of @cmd/start
        segment_s: float = SEGMENT_S  # length of a recording's MCAP segments (<= 0: one file)
        spare_buffer_s: float = 3.0  # what a standby spare holds of `keys` to bridge its takeover (0: none)
        spare_buffer_mb: float = 64.0  # and at most this much of it

    @classmethod
    def prepare(cls, params: Params, deployment: Any = None) -> None:
        """A standby spare generates the decoders before it takes over (~0.7 s off a restart), and
        listens to what a recording takes, to write what its takeover would miss."""
        warm_up(registered_types())
        if deployment is not None and params.spare_buffer_s > 0 and cls._spare is None:
            cls._spare = SpareListener(deployment.router, check_pattern(params.keys), params.spare_buffer_s,
                                       int(params.spare_buffer_mb * (1 << 20)))

    def __init__(self, node: Node, params: Params) -> None:
        self.node = node
        self.p = params
        self.recording: Recording | None = None
        self.last: dict | None = None
        self.repaired: list[dict] = []
        self.resumed: dict | None = None
        self.handoff: Handoff | None = None
        self.deployment_name = _deployment_name(self.deployment)
        self.note = Path(params.directory) / f".recording-{node.instance}.json"
        warm_up(registered_types())  # now, not while the first messages of a recording queue up
        spare, type(self)._spare = type(self)._spare, None
        self.spare_buffer: dict | None = None
        if spare is not None:
            self.spare_buffer = {"messages_held": len(spare.buffer), "seconds_held": round(spare.buffer.span_s(), 3)}
        self._resume(spare)
        if spare is not None and self.handoff is None:  # nothing to go on with: the buffer is dropped
            spare.close_soon()
        node.queryable("start", self.cmd_start)
        node.queryable("stop", self.cmd_stop)
        node.queryable("status", self.cmd_status)
        node.health_extra = self.health

    def _path(self, requested: Any) -> Path:
        if requested in (None, ""):
            return default_path(self.p.directory)
        if not isinstance(requested, str):
            raise ValueError(f"path must be a string or null, got {type(requested).__name__}")
        path = Path(requested)
        if path.is_dir() or requested.endswith("/"):
            return default_path(path)
        if path.exists():
            raise FileExistsError(f"{path} exists; give another path (recordings are never overwritten)")
        return path

    def cmd_start(self, req: dict) -> dict:
        if self.recording is not None:
            return {"ok": False, "error": f"already recording to {self.recording.writer.path}",
                    "path": str(self.recording.writer.path)}
        pattern = req.get("keys") or self.p.keys
        if not isinstance(pattern, str):
            raise ValueError(f"keys must be a string pattern, got {type(pattern).__name__}")
        path = self._path(req.get("path"))
        meta = {"deployment": self.deployment_name, "deployment_file": self.deployment,
                "recorder": f"{self.node.service}/{self.node.instance}", "clock": self.node.clock.mode}
        self.recording = Recording(self.node, path, pattern, meta, self.p.segment_s)
        write_note(self.note, {"path": str(path), "keys": pattern, "metadata": meta})
        self.node.set_status("ok", f"recording to {path}")
        self.node.log.info("recording started", extra=fields(path=str(path), keys=pattern))
        return {"ok": True, "path": str(path)}

    def _resume(self, spare: SpareListener | None = None) -> None:
        """Go on with the recording a killed recorder left noted, in its next segment; a listening
        ``spare`` first writes there what it received after the cut."""
        try:
            note = json.loads(self.note.read_text())
            path, pattern, meta = Path(note["path"]), str(note["keys"]), dict(note["metadata"])
        except FileNotFoundError:
            return
        except (OSError, ValueError, KeyError, TypeError) as exc:
            self.node.stats.count("bad_recording_note")
            self.node.log.warning("unreadable note of a recording in progress: not resumed",
                                  extra=fields(note=str(self.note), error=str(exc)[:200]))
            self.note.unlink(missing_ok=True)
            return
        index = next_segment_index(path)
        handoff = Handoff(spare) if spare is not None else None
        try:
            self.recording = Recording(self.node, path, pattern, {**meta, "resumed": "true"}, self.p.segment_s,
                                       first_index=index, handoff=handoff)
        except (OSError, ValueError) as exc:  # RecordingError is a ValueError
            self.node.stats.count("recording_not_resumed")
            self.node.set_status("error", f"cannot resume the recording {path}: {exc}")
            self.note.unlink(missing_ok=True)
            return
        self.resumed = {"path": str(path), "segment": index, "at_ns": time.time_ns()}
        if handoff is not None:  # read before run() repairs it: it ends where the repair ends
            handoff.cut = recording_cut(path, index)
            self.handoff = handoff
        self.node.stats.count("recording_resumed")
        self.node.set_status("ok", f"recording to {path} (resumed after a restart, segment {index})")
        self.node.log.warning("recording resumed after a restart", extra=fields(path=str(path), segment=index))

    async def cmd_stop(self, _req: dict) -> dict:
        if self.recording is None:
            return {"ok": False, "error": "not recording", "last": self.last}
        recording, self.recording = self.recording, None
        self.note.unlink(missing_ok=True)
        try:
            self.last = await recording.stop()
        except (OSError, RecordingError) as exc:
            self.node.set_status("error", f"closing {recording.writer.path} failed: {exc}")
            raise
        self.node.set_status("ok", "")
        self.node.log.info("recording stopped", extra=fields(
            path=self.last["path"], messages=sum(self.last["messages"].values()), bytes=self.last["bytes"]))
        return {"ok": True, **self.last}

    def cmd_status(self, _req: dict) -> dict:
        return {"ok": True, "recording": self.recording is not None,
                "current": self.recording.summary() if self.recording else None, "last": self.last}

    def health(self) -> dict:
        rec = self.recording.summary() if self.recording else None
        return {"recording": rec is not None, "path": rec["path"] if rec else None,
                "messages": rec["messages"] if rec else {}, "bytes": rec["bytes"] if rec else 0,
                "dropped": dropped(self.node.stats.errors), "last": self.last, "repaired_at_start": self.repaired,
                "resumed_at_start": self.resumed, "spare_buffer": self._spare_report()}

    def _spare_report(self) -> dict | None:
        """At a spare's takeover: what its buffer held, and what it gave a resumed recording."""
        if self.handoff is None or not self.handoff.done:
            return self.spare_buffer
        return self.handoff.report()

    async def run(self) -> None:
        """Repair what a crash left cut in the directory (off the loop: commands are served meanwhile)."""
        self.repaired = await asyncio.to_thread(repair_cut_segments, self.p.directory)
        await asyncio.Event().wait()

    async def close(self) -> None:
        if self.recording is not None:
            recording, self.recording = self.recording, None
            self.note.unlink(missing_ok=True)  # a clean shutdown ends the recording; only a crash resumes it
            self.last = await recording.stop()
            self.node.log.info("recording closed at shutdown", extra=fields(path=self.last["path"]))


def write_note(path: Path, note: dict) -> None:
    """Write the note of a recording in progress atomically (a crash mid-write leaves the old one)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(note))
    os.replace(tmp, path)


def dropped(errors: Counter[str]) -> dict[str, Any]:
    """``{"bad_payload": {key: n}, "unregistered_key": {key: n}, "queue_overflow": n}`` from node stats."""
    out: dict[str, Any] = {}
    for name, n in errors.items():
        kind, _, key = name.partition(":")
        if kind not in DROP_KINDS:
            continue
        if key:
            out.setdefault(kind, {})[key] = n
        else:
            out[kind] = n
    return out


def _deployment_name(path: str) -> str:
    if not path:
        return ""
    try:
        return load_deployment(path).name
    except Exception:  # the runtime already validated it; metadata is best effort
        return Path(path).stem
