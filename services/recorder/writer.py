"""MCAP files from wire bytes (no Zenoh here).

Profile ``ros2``, schemas ``ros2msg`` generated from the same typestore the services use, channel
encoding ``cdr``; payloads are the received bytes unchanged. Chunks are closed and fsync'ed at
least every ``flush_s`` seconds, so a recording killed with -9 is readable by stock readers up to
its last flushed chunk (``repair`` rewrites such a file with a summary for seeking readers).
"""

from __future__ import annotations

import os
import struct
import time
from collections import Counter
from pathlib import Path

from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from shared import msgs

CHUNK_BYTES = 512 * 1024
FLUSH_S = 1.0
_STAMP = struct.Struct("<iI")


def stamp_ns(payload: bytes) -> int | None:
    """Header stamp of a CDR message whose first field is a Time (every registered type): bytes 4..12."""
    if len(payload) < 12:
        return None
    sec, nanosec = _STAMP.unpack_from(payload, 4)
    if sec < 0 or nanosec >= 1_000_000_000:
        return None
    return sec * 1_000_000_000 + nanosec


class McapRecorder:
    def __init__(self, path: str | Path, metadata: dict[str, str] | None = None, flush_s: float = FLUSH_S) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = self.path.open("wb")
        self._writer = Writer(self._file, chunk_size=CHUNK_BYTES, compression=CompressionType.ZSTD)
        self._writer.start(profile="ros2", library="crossmodal")
        if metadata:
            self._writer.add_metadata("crossmodal", {k: str(v) for k, v in metadata.items()})
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self.counts: Counter[str] = Counter()
        self.bytes = 0
        self.flush_s = flush_s
        self._last_flush = time.monotonic()
        self.closed = False

    def _channel(self, key: str, msgtype: str) -> int:
        channel = self._channels.get(key)
        if channel is None:
            schema = self._schemas.get(msgtype)
            if schema is None:
                schema = self._writer.register_schema(msgtype, "ros2msg", msgs.schema_text(msgtype).encode())
                self._schemas[msgtype] = schema
            channel = self._writer.register_channel(key, "cdr", schema)
            self._channels[key] = channel
        return channel

    def write(self, key: str, msgtype: str, payload: bytes, log_time_ns: int | None = None) -> None:
        log_time = log_time_ns if log_time_ns is not None else time.time_ns()
        publish = stamp_ns(payload)
        self._writer.add_message(self._channel(key, msgtype), log_time=log_time, data=payload,
                                 publish_time=publish if publish is not None else log_time,
                                 sequence=self.counts[key])
        self.counts[key] += 1
        self.bytes += len(payload)
        if time.monotonic() - self._last_flush >= self.flush_s:
            self.flush()

    def flush(self) -> None:
        """Close the open chunk and push it to disk: everything written so far survives a kill."""
        self._writer.flush()
        self._file.flush()
        os.fsync(self._file.fileno())
        self._last_flush = time.monotonic()

    def close(self) -> None:
        if not self.closed:
            self._writer.finish()
            self._file.close()
            self.closed = True


def repair(src: str | Path, dst: str | Path) -> int:
    """Rewrite a cut recording (no footer) into a complete file; returns the messages recovered."""
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    ids: dict[tuple[str, int], int] = {}
    count = 0
    out = Writer(str(dst), chunk_size=CHUNK_BYTES, compression=CompressionType.ZSTD)
    out.start(profile="ros2", library="crossmodal repair")
    with open(src, "rb") as f:
        try:
            for record in StreamReader(f).records:
                if isinstance(record, Schema):
                    schemas[record.id] = record
                elif isinstance(record, Channel):
                    channels[record.id] = record
                elif isinstance(record, Message) and record.channel_id in channels:
                    ch = channels[record.channel_id]
                    if ("s", ch.schema_id) not in ids:
                        sc = schemas[ch.schema_id]
                        ids[("s", ch.schema_id)] = out.register_schema(sc.name, sc.encoding, sc.data)
                    if ("c", ch.id) not in ids:
                        schema_id = ids[("s", ch.schema_id)]
                        ids[("c", ch.id)] = out.register_channel(ch.topic, ch.message_encoding, schema_id)
                    out.add_message(ids[("c", ch.id)], record.log_time, record.data, record.publish_time,
                                    record.sequence)
                    count += 1
        except Exception:  # the cut tail (EndOfFile or a torn record): everything before it is kept
            pass
    out.finish()
    return count
