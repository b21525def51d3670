"""Message types: standard ROS 2 definitions plus ``xm_msgs`` from ``shared/msg``, encoded as CDR.

One rosbags typestore serves every service, the recorder and the tests, so the bytes on the
wire are the bytes in the MCAP file.
"""

from __future__ import annotations

from functools import cache
from pathlib import Path
from typing import Any

from rosbags.typesys import Stores, get_types_from_msg, get_typestore

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


def serialize(msg: Any, msgtype: str | None = None) -> bytes:
    return bytes(typestore().serialize_cdr(msg, msgtype or msg.__msgtype__))


def deserialize(data: bytes | memoryview, msgtype: str) -> Any:
    try:
        return typestore().deserialize_cdr(bytes(data), msgtype)
    except Exception as exc:  # rosbags raises several types on truncated or garbage input
        raise MessageError(f"payload of {len(data)} bytes is not a valid {msgtype}: {exc}") from exc


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
