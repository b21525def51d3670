"""The recorder's standby spare listens: what a recording would take, buffered until it takes over.

``SpareListener`` is opened by ``RecorderService.prepare`` in a spare (``--standby``): its own Zenoh
session, configured as the nodes' (shared/runtime/zsession.py) and connected to the deployment's
router, subscribes to the recorder's ``keys`` pattern and keeps raw payloads, stamped on arrival as
a recording stamps them, in a ``SpareBuffer`` (services/recorder/spare_buffer.py). ``recording_cut``
reads where the killed recorder's recording ends (its last whole chunk, which is also where the
repair of the cut segment ends). ``Handoff`` runs the takeover on the new recording's writer: it
holds the live stream until the live subscription brings a message the buffer holds too (from
then on nothing the buffer would miss is lost), stops the buffer, hands over the buffered messages
after the cut, then recognises the live copies of the ones it handed over.
"""

from __future__ import annotations

import io
import struct
import threading
import time
from pathlib import Path
from typing import Any

import zenoh
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, Message, Metadata
from mcap.stream_reader import breakup_chunk, get_chunk_data_stream

from services.recorder.spare_buffer import Cut, Entry, Overlap, SpareBuffer, after_cut, overlaps
from services.recorder.writer import MAGIC, METADATA_NAME
from shared.keys import is_internal
from shared.recording_files import segment_path
from shared.runtime.zsession import declare_subscriber, open_client

HANDOFF_WAIT_S = 0.5  # with no message seen by both subscriptions by then, the buffer stops anyway


class SpareListener:
    """A Zenoh session of its own buffering ``pattern``'s non-internal keys on Zenoh's thread."""

    def __init__(self, router: str, pattern: str, seconds: float, max_bytes: int) -> None:
        self.buffer = SpareBuffer(seconds, max_bytes)
        self.pattern = pattern
        self._internal: dict[str, bool] = {}
        self._session = open_client(router)
        try:
            self._sub = declare_subscriber(self._session, pattern, self._arrived)
        except Exception:
            self._session.close()
            raise

    def _arrived(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        internal = self._internal.get(key)
        if internal is None:
            internal = self._internal[key] = is_internal(key)
        if not internal:
            payload = sample.payload.to_bytes()
            self.buffer.add(key, payload, time.time_ns())

    def close(self) -> None:
        self.buffer.freeze()
        try:
            self._sub.undeclare()
        finally:
            self._session.close()

    def close_soon(self) -> None:
        """Freeze the buffer now, close the session on a thread (off the event loop)."""
        self.buffer.freeze()
        threading.Thread(target=self.close, name="spare-listener-close", daemon=True).start()


def recording_cut(path: str | Path, next_index: int) -> Cut | None:
    """Where the recording whose first segment is ``path`` ends, from its segments before
    ``next_index``, newest first: its last whole chunk, else (no message kept) the time its
    newest segment started; None when neither can be read."""
    started = None
    for index in range(next_index - 1, -1, -1):
        try:
            cut, seg_started = _segment_cut(segment_path(Path(path), index))
        except (OSError, ValueError, struct.error):
            continue
        if cut is not None:
            return cut
        started = started if started is not None else seg_started
    return Cut(started) if started is not None else None


def _segment_cut(path: Path) -> tuple[Cut | None, int | None]:
    chunks: list[tuple[int, int]] = []  # (offset, length) of each whole chunk record
    started = None
    with path.open("rb") as f:
        if f.read(len(MAGIC)) != MAGIC:
            raise ValueError(f"{path}: not an MCAP file")
        size = f.seek(0, io.SEEK_END)
        pos = len(MAGIC)
        while pos + 9 <= size:
            f.seek(pos)
            opcode, length = struct.unpack("<BQ", f.read(9))
            end = pos + 9 + length
            if end > size or opcode in (Opcode.DATA_END, Opcode.FOOTER):
                break
            if opcode == Opcode.CHUNK:
                chunks.append((pos + 9, length))
            elif opcode == Opcode.METADATA and started is None:
                meta = Metadata.read(ReadDataStream(io.BytesIO(f.read(length))))
                if meta.name == METADATA_NAME and meta.metadata.get("started_ns", "").isdigit():
                    started = int(meta.metadata["started_ns"])
            pos = end
        for offset, length in reversed(chunks):
            f.seek(offset)
            try:
                records = breakup_chunk(Chunk.read(ReadDataStream(io.BytesIO(f.read(length)))), validate_crc=True)
            except Exception:  # a chunk torn or damaged on disk: the one before it
                continue
            messages = [r for r in records if isinstance(r, Message)]
            if not messages:
                continue
            topics = {r.id: r.topic for r in records if isinstance(r, Channel)}
            missing = {m.channel_id for m in messages} - set(topics)
            if missing:
                topics.update(_channels(f, chunks, missing))
            last: dict[str, tuple[bytes, int]] = {}
            for m in messages:
                if m.channel_id in topics:
                    last[topics[m.channel_id]] = (bytes(m.data), m.log_time)
            return Cut(max(m.log_time for m in messages), last), started
    return None, started


def _channels(f: Any, chunks: list[tuple[int, int]], wanted: set[int]) -> dict[int, str]:
    """Topics of the channel ids ``wanted``, from the chunks in order (a channel is written into
    the chunk of its key's first message)."""
    topics: dict[int, str] = {}
    for offset, length in chunks:
        f.seek(offset)
        try:
            stream, n = get_chunk_data_stream(Chunk.read(ReadDataStream(io.BytesIO(f.read(length)))))
        except Exception:
            continue
        while stream.count < n:
            opcode, rec_len = stream.read1(), stream.read8()
            if opcode == Opcode.CHANNEL:
                channel = Channel.read(stream)
                if channel.id in wanted:
                    topics[channel.id] = channel.topic
                    if len(topics) == len(wanted):
                        return topics
            else:
                stream.read(rec_len)
    return topics


class Handoff:
    """The takeover of a recording by a listening spare, run by the new recording's writer."""

    def __init__(self, listener: SpareListener) -> None:
        self.listener = listener
        self.cut: Cut | None = None
        self.live_from_ns = 0
        self.started = 0.0
        self.done = False
        self.overlap: Overlap | None = None
        self.held = 0
        self.held_s = 0.0
        self.written = 0
        self.duplicates = 0

    def live_from(self, t_ns: int) -> None:
        """The live subscriptions are declared from ``t_ns`` on."""
        self.live_from_ns = t_ns
        self.started = time.monotonic()

    def take(self, pending: Any, takes: Any, is_state: Any, force: bool = False) -> list[Entry] | None:
        """The buffered messages to write before the live ones, once the live subscription has shown
        it is on (or ``force``, or after ``HANDOFF_WAIT_S``); None until then."""
        if not force and time.monotonic() - self.started < HANDOFF_WAIT_S:
            live = [entry for entry in list(pending) if not is_state(entry[0])]
            if not overlaps(self.listener.buffer.since(self.live_from_ns), live):
                return None
        self.held_s = self.listener.buffer.span_s()
        entries = self.listener.buffer.freeze()
        self.listener.close_soon()
        self.held = len(entries)
        backlog = after_cut(entries, self.cut, takes) if self.cut is not None else []
        self.overlap = Overlap(backlog, self.live_from_ns, is_state)
        self.written = len(backlog)
        self.done = True
        return backlog

    def is_copy(self, key: str, payload: bytes) -> bool:
        if self.overlap is None or not self.overlap.is_copy(key, payload):
            return False
        self.duplicates += 1
        return True

    def report(self) -> dict:
        return {"messages_held": self.held, "seconds_held": round(self.held_s, 3), "written": self.written,
                "duplicates_skipped": self.duplicates, "cut_ns": self.cut.time_ns if self.cut else None}
