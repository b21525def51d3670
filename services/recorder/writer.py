"""MCAP files from wire bytes, and reading them back (no Zenoh here).

Profile ``ros2``, schemas ``ros2msg`` generated from the typestore the services use, channels
``cdr``; each payload is stored exactly as received, so the wire format is the file format.

Crash safety: messages go into LZ4-compressed chunks of ~1 MB; a chunk is closed, written and
fsync'ed when full and at least every ``flush_s`` seconds. A recording cut by ``kill -9`` or a power loss
therefore ends after its last complete chunk, but has no summary section and no footer:

* seeking readers (``mcap_ros2.reader.read_ros2_messages(path)``, rosbags ``AnyReader``) refuse it;
* streaming readers read it up to the cut: ``read_messages(path)`` here, or
  ``mcap.reader.NonSeekingReader(f).iter_messages(log_time_order=False)`` catching the
  exception raised at the cut;
* ``repair(src, dst)`` (``xm record --repair FILE``) rewrites it as a complete file.
"""

from __future__ import annotations

import fcntl
import json
import os
import socket
import time
from collections import Counter
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any, BinaryIO

from mcap.reader import NonSeekingReader, SeekingReader
from mcap.records import Channel, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from shared import msgs
from shared.recording_files import recording_segments

MAGIC = b"\x89MCAP0\r\n"
CHUNK_BYTES = 1024 * 1024
FLUSH_S = 0.25  # what a kill -9 of the recorder can lose, on top of its restart
# LZ4: on camera frames (already JPEG) zstd gains nothing and costs the recorder ~4 % of a core
# more at a rig's rates; both squeeze the raw tactile and state streams alike (bench/recorder.py)
COMPRESSION = CompressionType.LZ4
METADATA_NAME = "crossmodal"
SUMMARY_NAME = "crossmodal.summary"
LIBRARY = "crossmodal recorder"


class RecordingError(ValueError):
    """A file that is not a usable MCAP recording, or a writer used after close."""


def stamp_ns(msg: Any) -> int | None:
    """The time a decoded message carries: ``header.stamp``, or ``clock`` for rosgraph Clock."""
    stamp = getattr(getattr(msg, "header", None), "stamp", None)
    if stamp is None:
        stamp = getattr(msg, "clock", None)
    sec, nanosec = getattr(stamp, "sec", None), getattr(stamp, "nanosec", None)
    if not isinstance(sec, int) or not isinstance(nanosec, int) or sec < 0:
        return None
    return sec * 1_000_000_000 + nanosec


def check_payload(msgtype: str, payload: bytes) -> int | None:
    """Decode ``payload`` as ``msgtype`` (raises ``msgs.MessageError``); returns its stamp in ns."""
    return payload_checker(msgtype)(payload)


@cache
def payload_checker(msgtype: str) -> Callable[[bytes], int | None]:
    """``check_payload`` for one type, looked up once per channel: the type's decoder, and
    ``stamp_ns`` only for a type that has a stamp. MessageError for an unknown type."""
    decode = msgs.decoder(msgtype)
    fields = msgs.msg_class(msgtype).__dataclass_fields__
    if "header" not in fields and "clock" not in fields:
        def check(payload: bytes) -> None:
            decode(payload)
            return None
        return check
    return lambda payload: stamp_ns(decode(payload))


def warm_up(msgtypes: Iterable[str]) -> None:
    """Generate the decoders and schemas of these types now (~50 ms each): done lazily on a
    key's first message, it would stall the subscription queue while messages pile up."""
    store = msgs.typestore()
    for msgtype in msgtypes:
        store.get_msgdef(msgtype)
        msgs.schema_text(msgtype)


@dataclass
class Summary:
    path: str
    messages: dict[str, int]
    bytes: int
    seconds: float
    chunks: int
    rates_hz: dict[str, float]  # per key, from the first and last receive times
    durable: int  # messages in chunks already fsync'ed: what a kill now would keep

    def as_dict(self) -> dict:
        return {"path": self.path, "messages": dict(self.messages), "bytes": self.bytes,
                "seconds": round(self.seconds, 3), "chunks": self.chunks, "durable_messages": self.durable,
                "rates_hz": {k: round(v, 2) for k, v in self.rates_hz.items()}}


class McapRecorder:
    """One MCAP file being written; ``write`` takes wire bytes and the key's message type.

    ``validate=True`` decodes each payload first: a payload that does not decode raises
    ``msgs.MessageError`` and is not written, so stock readers never meet an undecodable message.
    """

    def __init__(self, path: str | Path, metadata: dict[str, Any] | None = None, flush_s: float = FLUSH_S,
                 chunk_bytes: int = CHUNK_BYTES, validate: bool = True) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = _CountingFile(self.path.open("wb"))
        # Held while the file is written: a recorder starting up repairs only cut files nobody holds.
        fcntl.flock(self._file.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        self._writer = Writer(self._file, chunk_size=chunk_bytes, compression=COMPRESSION)
        self._writer.start(profile="ros2", library=LIBRARY)
        self.metadata = {"host": socket.gethostname(), "started_ns": str(time.time_ns()),
                         "started": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
        self.metadata.update({k: _text(v) for k, v in (metadata or {}).items()})
        self._writer.add_metadata(METADATA_NAME, self.metadata)
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, tuple[int, Callable[[bytes], int | None]]] = {}  # key -> (id, checker)
        self.counts: Counter[str] = Counter()
        self.span_ns: dict[str, list[int]] = {}  # key -> [first, last] log time
        self.bytes = 0
        self.chunks = 0
        self.durable = 0
        self._pending = 0  # messages in the open chunk
        self.flush_s = flush_s
        self.validate = validate
        self.started = time.monotonic()
        self._last_flush = self.started
        self._synced_pos = self._file.pos
        self._sync()
        self.closed = False

    def _channel(self, key: str, msgtype: str) -> tuple[int, Callable[[bytes], int | None]]:
        check = payload_checker(msgtype)  # an unknown type raises MessageError before a channel exists
        schema = self._schemas.get(msgtype)
        if schema is None:
            schema = self._writer.register_schema(msgtype, "ros2msg", msgs.schema_text(msgtype).encode())
            self._schemas[msgtype] = schema
        self._channels[key] = (self._writer.register_channel(key, "cdr", schema), check)
        return self._channels[key]

    def write(self, key: str, msgtype: str, payload: bytes, log_time_ns: int | None = None) -> None:
        """Append one message; log time defaults to now, publish time is its stamp when it has one."""
        if self.closed:
            raise RecordingError(f"{self.path}: recording already closed")
        channel, check = self._channels.get(key) or self._channel(key, msgtype)
        stamp = check(payload) if self.validate else None
        log_time = log_time_ns if log_time_ns is not None else time.time_ns()
        n = self.counts[key]
        self._writer.add_message(channel, log_time, payload, log_time if stamp is None else stamp, n & 0xFFFFFFFF)
        self.counts[key] = n + 1
        self._pending += 1
        self.bytes += len(payload)
        span = self.span_ns.get(key)
        if span is None:
            self.span_ns[key] = [log_time, log_time]
        else:
            span[1] = log_time
        if self._file.pos != self._synced_pos:  # the writer closed a full chunk: make it durable now
            self.chunks += 1
            self._sync()
            self._durable_now()
        elif time.monotonic() - self._last_flush >= self.flush_s:
            self.flush()

    def maybe_flush(self, now: float | None = None) -> bool:
        """Flush when the open chunk is older than ``flush_s``; call it from a timer too."""
        now = time.monotonic() if now is None else now
        if now - self._last_flush < self.flush_s:
            return False
        self.flush()
        return True

    def flush(self) -> None:
        """Close the open chunk and fsync: everything written so far survives a kill."""
        if self.closed:
            return
        before = self._file.pos
        self._writer.flush()
        if self._file.pos != before:
            self.chunks += 1
        self._sync()
        self._durable_now()

    def _durable_now(self) -> None:
        self.durable += self._pending
        self._pending = 0

    def _sync(self) -> None:
        self._file.flush()
        os.fsync(self._file.fileno())
        self._synced_pos = self._file.pos
        self._last_flush = time.monotonic()

    def rates(self) -> dict[str, float]:
        """Messages per second of each key over its own first..last span (0 below two messages)."""
        return {k: (self.counts[k] - 1) / ((b - a) * 1e-9) if b > a else 0.0
                for k, (a, b) in self.span_ns.items()}

    def summary(self) -> Summary:
        return Summary(str(self.path), dict(self.counts), self.bytes, time.monotonic() - self.started,
                       self.chunks, self.rates(), self.durable)

    def close(self) -> Summary:
        """Write the message counts, the summary section and the footer."""
        if not self.closed:
            self.flush()
            summary = self.summary()
            self._writer.add_metadata(SUMMARY_NAME, {
                "stopped_ns": str(time.time_ns()), "seconds": f"{summary.seconds:.3f}",
                "messages": json.dumps(summary.messages, sort_keys=True), "bytes": str(self.bytes)})
            self._writer.finish()
            self._file.flush()
            os.fsync(self._file.fileno())
            self._file.close()
            self.closed = True
            self._summary = summary
        return self._summary


class _CountingFile:
    """A file written only at its end, that knows its size without asking the kernel (``tell`` of
    a buffered file is a system call, and the writer asks after every message)."""

    def __init__(self, file: BinaryIO) -> None:
        self._f = file
        self.pos = file.tell()

    def write(self, data: bytes | bytearray | memoryview) -> int:
        n = self._f.write(data)
        self.pos += n
        return n

    def tell(self) -> int:
        return self.pos

    def flush(self) -> None:
        self._f.flush()

    def fileno(self) -> int:
        return self._f.fileno()

    def close(self) -> None:
        self._f.close()


def _text(value: Any) -> str:
    return value if isinstance(value, str) else json.dumps(value, default=str)


# --- reading ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class Stored:
    key: str
    msgtype: str
    log_time: int
    publish_time: int
    data: bytes


def check_mcap(path: str | Path) -> None:
    """Raise RecordingError with a readable reason unless ``path`` starts like an MCAP file."""
    path = Path(path)
    if not path.exists():
        raise RecordingError(f"{path}: no such file")
    if path.is_dir():
        raise RecordingError(f"{path}: is a directory, not an MCAP file")
    with path.open("rb") as f:
        head = f.read(len(MAGIC))
    if head != MAGIC:
        raise RecordingError(f"{path}: not an MCAP file (it does not start with the MCAP magic bytes)")


def is_being_written(path: str | Path) -> bool:
    """True while a live McapRecorder holds ``path`` (its lock goes with the process)."""
    try:
        with Path(path).open("rb") as f:
            fcntl.flock(f.fileno(), fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    except OSError:
        return False
    return False


def is_complete(path: str | Path) -> bool:
    """True when the file ends with a footer (it was closed, not cut)."""
    with Path(path).open("rb") as f:
        f.seek(0, os.SEEK_END)
        if f.tell() < 2 * len(MAGIC):
            return False
        f.seek(-len(MAGIC), os.SEEK_END)
        return f.read() == MAGIC


def recording_files(source: str | Path | Iterable[str | Path]) -> list[Path]:
    """The MCAP segments of a recording (a segment's path, a directory, or a list of files) in order;
    RecordingError when there are none or one is not an MCAP file."""
    files = recording_segments(source)
    if not files:
        raise RecordingError(f"{source}: no MCAP files (*.mcap) in this directory")
    for f in files:
        check_mcap(f)
    return files


def read_messages(source: str | Path | Iterable[str | Path], keys: set[str] | None = None,
                  cut: list[str] | None = None) -> Iterator[Stored]:
    """Messages of a recording, segment after segment, each in log-time order; complete segments are
    read with the seeking reader, a cut one up to its last whole chunk.

    ``source``: a segment's path (the recording's other segments are found beside it), a directory
    of segments, or a list of files. For a cut file, a line saying where it ended is appended to ``cut``."""
    for path in recording_files(source):
        yield from _read_file(path, keys, cut)


def read_segment(path: str | Path, keys: set[str] | None = None, cut: list[str] | None = None) -> Iterator[Stored]:
    """Messages of one MCAP file alone (not the segments beside it), read as ``read_messages`` reads each."""
    check_mcap(path)
    yield from _read_file(Path(path), keys, cut)


def _read_file(path: Path, keys: set[str] | None, cut: list[str] | None) -> Iterator[Stored]:
    with Path(path).open("rb") as f:
        if is_complete(path):
            source = SeekingReader(f).iter_messages(topics=keys, log_time_order=True)
            for schema, channel, message in source:
                yield Stored(channel.topic, schema.name if schema else "", message.log_time,
                             message.publish_time, message.data)
            return
        source = NonSeekingReader(f).iter_messages(topics=keys, log_time_order=False)
        n = 0
        try:
            for schema, channel, message in source:
                n += 1
                yield Stored(channel.topic, schema.name if schema else "", message.log_time,
                             message.publish_time, message.data)
        except Exception as exc:  # EndOfFile, struct.error, ...: the torn tail of a killed recording
            if cut is not None:
                cut.append(f"{path}: no footer, cut after {n} messages ({type(exc).__name__}); "
                           f"`xm record --repair {path}` writes a complete copy")


def read_metadata(path: str | Path) -> dict[str, dict[str, str]]:
    """Metadata records by name (streaming, so cut files work too)."""
    check_mcap(path)
    out: dict[str, dict[str, str]] = {}
    with Path(path).open("rb") as f:
        try:
            for record in StreamReader(f).records:
                if isinstance(record, Metadata):
                    out[record.name] = dict(record.metadata)
        except Exception:  # a cut tail: what came before it is kept
            pass
    return out


def repair(src: str | Path, dst: str | Path) -> int:
    """Rewrite a cut recording (no footer) into a complete file; returns the messages recovered."""
    check_mcap(src)
    if Path(src).resolve() == Path(dst).resolve():
        raise RecordingError(f"{dst}: repair needs a different output file than its input")
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    out_schema: dict[int, int] = {}
    out_channel: dict[int, int] = {}
    count = 0
    with Path(dst).open("wb") as out_file, Path(src).open("rb") as f:
        out = Writer(out_file, chunk_size=CHUNK_BYTES, compression=COMPRESSION)
        out.start(profile="ros2", library=f"{LIBRARY} (repair)")
        try:
            for record in StreamReader(f).records:
                if isinstance(record, Schema):
                    schemas[record.id] = record
                elif isinstance(record, Channel):
                    channels[record.id] = record
                elif isinstance(record, Metadata):
                    data = dict(record.metadata)
                    if record.name == METADATA_NAME:
                        data["repaired_from"] = str(src)
                    out.add_metadata(record.name, data)
                elif isinstance(record, Message) and record.channel_id in channels:
                    ch = channels[record.channel_id]
                    if ch.id not in out_channel:
                        if ch.schema_id not in out_schema:
                            sc = schemas[ch.schema_id]
                            out_schema[ch.schema_id] = out.register_schema(sc.name, sc.encoding, sc.data)
                        out_channel[ch.id] = out.register_channel(ch.topic, ch.message_encoding,
                                                                  out_schema[ch.schema_id], ch.metadata)
                    out.add_message(out_channel[ch.id], record.log_time, record.data, record.publish_time,
                                    record.sequence)
                    count += 1
        except Exception:  # the cut tail (EndOfFile or a torn record): everything before it is kept
            pass
        out.finish()
    return count
