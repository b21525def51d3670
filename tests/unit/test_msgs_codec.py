"""The message codec against rosbags' own, byte for byte and field for field, on every registered
type and every type of the typestore (pure)."""

from __future__ import annotations

import numpy as np
import pytest
from rosbags.serde.utils import ndtype
from rosbags.typesys.base import Nodetype

from shared import cdr, keys, msgs
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


def random_message(store, msgtype: str, rng: np.random.Generator):
    """A message of ``msgtype`` with every field random: strings and sequences of random lengths
    (so every alignment after them occurs), numbers over their type's whole range."""
    def base(name: str):
        if name == "string":
            return "".join(chr(c) for c in rng.integers(32, 0x800, rng.integers(0, 10)))
        dtype = np.dtype(getattr(np, ndtype(name)))
        return array(name, 1)[0].item() if dtype.kind != "b" else bool(rng.integers(0, 2))

    def array(name: str, n: int):
        if name == "string":
            return [base(name) for _ in range(n)]
        dtype = np.dtype(getattr(np, ndtype(name)))
        if dtype.kind == "b":
            return rng.integers(0, 2, n).astype(dtype)
        if dtype.kind == "f":
            return (rng.standard_normal(n) * 1e3).astype(dtype)
        return rng.integers(0, 256, n * dtype.itemsize, dtype=np.uint8).view(dtype)

    def field(kind, arg):
        if kind == Nodetype.BASE:
            return base(arg[0])
        if kind == Nodetype.NAME:
            return message(arg)
        sub, length = arg
        n = length if kind == Nodetype.ARRAY else int(rng.integers(0, 4))
        return [message(sub[1]) for _ in range(n)] if sub[0] == Nodetype.NAME else array(sub[1][0], n)

    def message(name: str):
        return store.types[name](*(field(*desc) for _, desc in store.get_msgdef(name).fields))

    return message(msgtype)


def assert_same_fields(ours, theirs, path: str = "msg") -> None:
    assert type(ours) is type(theirs), path
    if isinstance(ours, np.ndarray):
        assert ours.dtype == theirs.dtype and np.array_equal(ours, theirs, equal_nan=ours.dtype.kind == "f"), path
    elif isinstance(ours, list):
        assert len(ours) == len(theirs), path
        for i, (a, b) in enumerate(zip(ours, theirs, strict=True)):
            assert_same_fields(a, b, f"{path}[{i}]")
    elif hasattr(ours, "__dataclass_fields__"):
        for name in ours.__dataclass_fields__:
            if name != "__msgtype__":
                assert_same_fields(getattr(ours, name), getattr(theirs, name), f"{path}.{name}")
    else:
        assert ours == theirs or (ours != ours and theirs != theirs), (path, ours, theirs)


def test_generated_codecs_match_rosbags_on_every_type_of_the_store():
    store = msgs.typestore()
    rng = np.random.default_rng(11)
    for msgtype in sorted(store.types):
        write, read = cdr.writer(store, msgtype), cdr.reader(store, msgtype)
        for _ in range(6):
            msg = random_message(store, msgtype, rng)
            theirs = bytes(store.serialize_cdr(msg, msgtype))
            pieces, size = write(msg)
            assert b"".join(pieces) == theirs and size == len(theirs), msgtype
            decoded, end = read(theirs)
            assert end == len(theirs), msgtype
            assert_same_fields(decoded, store.deserialize_cdr(theirs, msgtype), msgtype)


@pytest.mark.parametrize("spec", keys.REGISTRY, ids=lambda s: s.key)
def test_truncated_or_padded_payloads_raise_message_error_only(spec):
    store = msgs.typestore()
    rng = np.random.default_rng(5)
    whole = msgs.serialize(random_message(store, spec.msgtype, rng), spec.msgtype)
    for cut in sorted({*range(0, len(whole), max(1, len(whole) // 40)), len(whole) - 1}):
        with pytest.raises(msgs.MessageError):
            msgs.deserialize(whole[:cut], spec.msgtype)
    with pytest.raises(msgs.MessageError):
        msgs.deserialize(whole + bytes(8), spec.msgtype)
