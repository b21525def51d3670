"""The message codec against rosbags' own, byte for byte, on every registered type (pure)."""

from __future__ import annotations

import numpy as np
import pytest

from shared import keys, msgs
from tests.bad_messages import good


def randomized(msg, rng: np.random.Generator):
    """The message with every numeric array refilled with random values of its dtype."""
    for name in getattr(msg, "__dataclass_fields__", {}):
        if name == "__msgtype__":
            continue
        value = getattr(msg, name)
        if isinstance(value, np.ndarray) and value.dtype.kind in "fiu":
            info = np.finfo(value.dtype) if value.dtype.kind == "f" else np.iinfo(value.dtype)
            fresh = rng.uniform(-1e3, 1e3, value.shape) if value.dtype.kind == "f" else \
                rng.integers(max(info.min, -1000), min(info.max, 1000), value.shape, endpoint=True)
            setattr(msg, name, fresh.astype(value.dtype))
        elif isinstance(value, list):
            for item in value:
                randomized(item, rng)
        elif hasattr(value, "__dataclass_fields__"):
            randomized(value, rng)
    return msg


@pytest.mark.parametrize("spec", keys.REGISTRY, ids=lambda s: s.key)
def test_encoding_is_byte_for_byte_rosbags_and_decodes_both_byte_orders(spec):
    store = msgs.typestore()
    rng = np.random.default_rng(7)
    for _ in range(5):
        msg = randomized(good(spec.msgtype, 1000.0), rng)
        ours = msgs.serialize(msg, spec.msgtype)
        assert ours == bytes(store.serialize_cdr(msg, spec.msgtype))
        assert msgs.serialize(msgs.deserialize(ours, spec.msgtype), spec.msgtype) == ours
        big = bytes(store.serialize_cdr(msg, spec.msgtype, little_endian=False))
        assert msgs.serialize(msgs.deserialize(big, spec.msgtype), spec.msgtype) == ours


def test_bad_payloads_raise_message_error():
    t = "sensor_msgs/msg/JointState"
    ok = msgs.serialize(good(t, 1.0), t)
    for bad in (b"", b"\x00", b"\x01\x00\x00\x00" + ok[4:], ok[:-9], ok + b"\x00" * 8):
        with pytest.raises(msgs.MessageError):
            msgs.deserialize(bad, t)
    with pytest.raises(msgs.MessageError, match="unknown message type"):
        msgs.deserialize(ok, "xm_msgs/msg/NoSuchType")
