"""Message types: standard ROS 2 definitions plus ``xm_msgs`` from ``shared/msg``, encoded as CDR.

One rosbags typestore serves every service, the recorder and the tests, so the bytes on the
wire are the bytes in the MCAP file. ``serialize`` and ``deserialize`` run a codec generated once
per type (shared/cdr.py; the typestore's own for a big-endian payload or host, or a type the
generator does not handle): no per-message lookups, no copy of the payload (arrays of a decoded
message are read-only views into it).
"""

from __future__ import annotations

import sys
from functools import cache, partial
from pathlib import Path
from struct import pack_into
from typing import Any

from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from shared import cdr

MSG_DIR = Path(__file__).parent / "msg"
PACKAGE = "xm_msgs"


class MessageError(ValueError):
    """A payload that does not decode as the message type its key promises."""


@cache
def typestore() -> Any:
    store = get_typestore(Stores.ROS2_JAZZY)
    types: dict = {}
    for path in sorted(MSG_DIR.glob("*.msg")):
        types.update(get_types_from_msg(path.read_text(), f"{PACKAGE}/msg/{path.stem}"))
    store.register(types)
    return store


def msg_class(msgtype: str) -> type:
    try:
        return typestore().types[msgtype]
    except KeyError:
        raise MessageError(f"unknown message type {msgtype!r}") from None


LITTLE_ENDIAN = sys.byteorder == "little"
CDR_HEADER = 4  # encapsulation kind (2 bytes: 0, 1 for little endian) and options
CDR_PADDING_MAX = 3  # a message may end in up to 3 bytes of alignment padding


@cache
def _msgdef(msgtype: str) -> Any:
    try:
        return typestore().get_msgdef(msgtype)
    except Exception:  # rosbags raises its own error for an unknown type
        raise MessageError(f"unknown message type {msgtype!r}") from None


@cache
def _writer(msgtype: str) -> Any:
    """The generated writer of ``msgtype`` (None: use the typestore's)."""
    _msgdef(msgtype)  # an unknown type raises MessageError
    if not LITTLE_ENDIAN:
        return None
    try:
        return cdr.writer(typestore(), msgtype)
    except cdr.UnsupportedTypeError:
        return None


@cache
def _decoder_le(msgtype: str) -> Any:
    """The generated decoder of ``msgtype`` (None: use the typestore's); it hands a payload that
    is not little-endian to the typestore's."""
    _msgdef(msgtype)  # an unknown type raises MessageError
    if not LITTLE_ENDIAN:
        return None
    try:
        return cdr.decoder(typestore(), msgtype, MessageError, partial(_deserialize_store, msgtype=msgtype),
                           CDR_PADDING_MAX)
    except cdr.UnsupportedTypeError:
        return None


@cache
def pieces_writer(msgtype: str) -> Any:
    """``write(msg) -> (pieces, size)``: the CDR payload of a ``msgtype`` message as bytes-like
    pieces to join or copy in order, and its size in bytes (a publisher looks this up once)."""
    write = _writer(msgtype)
    if write is not None:
        return write

    def whole(msg: Any) -> tuple[list, int]:
        data = serialize(msg, msgtype)
        return [data], len(data)
    return whole


def serialize(msg: Any, msgtype: str | None = None) -> bytes:
    """CDR bytes of ``msg`` in the host's byte order, as ``typestore().serialize_cdr`` writes them."""
    write = _writer(msgtype or msg.__msgtype__)
    if write is not None:
        return b"".join(write(msg)[0])
    d = _msgdef(msgtype or msg.__msgtype__)
    size = CDR_HEADER + d.getsize_cdr(0, msg, typestore())
    out = bytearray(size)
    view = memoryview(out)
    pack_into("BB", view, 0, 0, LITTLE_ENDIAN)
    write = d.serialize_cdr_le if LITTLE_ENDIAN else d.serialize_cdr_be
    end = write(view[CDR_HEADER:], 0, msg, typestore())
    if end + CDR_HEADER != size:
        raise MessageError(f"{msgtype or msg.__msgtype__}: wrote {end + CDR_HEADER} of {size} bytes")
    return bytes(out)


def deserialize(data: bytes | bytearray | memoryview, msgtype: str) -> Any:
    """The message in a CDR payload (either byte order); MessageError if it is not one of ``msgtype``."""
    fast = _decoder_le(msgtype)
    return fast(data) if fast is not None else _deserialize_store(data, msgtype)


def _deserialize_store(data: bytes | bytearray | memoryview, msgtype: str) -> Any:
    """``deserialize`` through the typestore's codec (a big-endian payload or host, or a type the
    generator does not handle)."""
    try:
        if len(data) < CDR_HEADER or data[0] != 0 or data[1] > 1:
            raise ValueError("invalid or unsupported CDR encapsulation")
        d = _msgdef(msgtype)
        read = d.deserialize_cdr_le if data[1] else d.deserialize_cdr_be
        msg, end = read(memoryview(data)[CDR_HEADER:], 0, d.cls, typestore())
        end += CDR_HEADER
        if end + CDR_PADDING_MAX < len(data):
            raise ValueError(f"{len(data) - end} bytes beyond the message")
    except MessageError:
        raise
    except Exception as exc:  # the typestore's code raises several types on truncated or garbage input
        raise MessageError(f"payload of {len(data)} bytes is not a valid {msgtype}: {exc}") from exc
    return msg


@cache
def decoder(msgtype: str) -> Any:
    """``deserialize`` for one type, looked up once (a subscription's per-key decoder): the
    generated decoder itself for a type it handles."""
    fast = _decoder_le(msgtype)
    return fast if fast is not None else partial(_deserialize_store, msgtype=msgtype)


def schema_text(msgtype: str) -> str:
    """The ros2msg schema an MCAP channel of this type needs."""
    return typestore().generate_msgdef(msgtype, ros_version=2)[0]


def make(msgtype: str, **fields: Any) -> Any:
    return msg_class(msgtype)(**fields)


def stamp(seconds: float) -> Any:
    sec = int(seconds // 1)
    nanosec = int(round((seconds - sec) * 1e9))
    if nanosec >= 1_000_000_000:
        sec, nanosec = sec + 1, nanosec - 1_000_000_000
    return make("builtin_interfaces/msg/Time", sec=sec, nanosec=nanosec)


def header(seconds: float, frame_id: str = "world") -> Any:
    return make("std_msgs/msg/Header", stamp=stamp(seconds), frame_id=frame_id)


def stamp_seconds(time_msg: Any) -> float:
    return time_msg.sec + time_msg.nanosec * 1e-9
