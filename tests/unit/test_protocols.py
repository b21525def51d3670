"""Properties every device-protocol stream decoder shares (tactile readout, robot control board),
fuzzed with hypothesis against the committed test vectors: it never raises, every byte fed is in a
good frame, discarded (and counted) or still buffered, garbage never passes the CRC, and good frames
after any garbage are recovered. Protocol-specific cases live in test_tactile_protocol.py and
test_robot_board_protocol.py."""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from shared.protocols import robot_board as rb
from shared.protocols import tactile


@dataclass(frozen=True)
class Protocol:
    decoder: Callable[[], object]
    encode: Callable[[object], bytes]
    frames: list[bytes]  # the committed vectors' frames


def _vector_frames(path, only=lambda case: True) -> list[bytes]:
    return [bytes.fromhex(c["bytes"]) for c in json.loads(path.read_text()) if only(c)]


PROTOCOLS = {
    "tactile": Protocol(tactile.StreamDecoder, tactile.encode_frame,
                        _vector_frames(tactile.VECTORS_PATH, lambda c: "real" in c)),
    "robot_board": Protocol(rb.StreamDecoder, rb.encode,
                            _vector_frames(Path(rb.__file__).parent / "vectors" / "robot_board.json")),
}
both = pytest.mark.parametrize("proto", list(PROTOCOLS.values()), ids=list(PROTOCOLS))
frame_of = st.sampled_from  # a vector frame of the protocol under test


def accounted(decoder) -> int:
    """Bytes in good frames, discarded (and counted) or still buffered: all that was fed."""
    s = decoder.stats
    return s["frame_bytes"] + s["bytes_discarded"] + len(decoder.frames.buffer)


@both
@settings(max_examples=150, deadline=None)
@given(data=st.data(), split=st.integers(min_value=1, max_value=700))
def test_decoder_never_raises_and_counts_every_rejected_byte(proto, data, split):
    chunks = data.draw(st.lists(st.one_of(st.binary(max_size=300), frame_of(proto.frames)), max_size=10))
    stream = b"".join(chunks)
    decoder = proto.decoder()
    out = []
    for i in range(0, len(stream), split):  # arbitrary read boundaries
        out += decoder.feed(stream[i:i + split])
    assert accounted(decoder) == len(stream)
    assert len(out) <= sum(1 for c in chunks if c in proto.frames)  # garbage never passes the CRC


@both
@settings(max_examples=150, deadline=None)
@given(data=st.data(), garbage=st.binary(max_size=2000))
def test_good_frames_after_any_garbage_are_recovered(proto, data, garbage):
    good = data.draw(frame_of(proto.frames))
    decoder = proto.decoder()
    # A partial frame inside the garbage can hide at most one following frame: send three.
    out = decoder.feed(garbage + good * 3)
    assert len(out) >= 2 and all(proto.encode(m) == good for m in out[-2:])
    assert accounted(decoder) == len(garbage) + 3 * len(good)
