"""Device protocols against their committed test vectors, plus property tests of the decoders."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from shared.protocols import robot_board as rb
from shared.protocols import tactile

VECTORS = Path(__file__).resolve().parents[2] / "shared/protocols/vectors"


def test_board_vectors():
    for case in json.loads((VECTORS / "robot_board.json").read_text()):
        data = bytes.fromhex(case["bytes"])
        (msg,) = rb.StreamDecoder().feed(data)
        if "command" in case:
            c = case["command"]
            assert msg.sequence == c["sequence"] and msg.mode.tolist() == c["mode"]
            np.testing.assert_allclose(msg.position, c["position"], rtol=1e-6)
            assert rb.encode_command(msg) == data
        elif "feedback" in case:
            assert msg.watchdog_expired and msg.timestamp_us == case["feedback"]["timestamp_us"]
            assert msg.last_command_us == case["feedback"]["last_command_us"]
            assert rb.encode_feedback(msg) == data
        else:
            assert msg.watchdog_timeout_us == case["config"]["watchdog_timeout_us"]


FRAMES = [bytes.fromhex(c["bytes"]) for c in json.loads((VECTORS / "tactile.json").read_text()) if "real" in c]


def accounted(decoder) -> int:
    """Every byte fed is in a frame, discarded (and counted), or still buffered."""
    st_ = decoder.stats
    return st_["frame_bytes"] + st_["bytes_discarded"] + len(decoder.frames.buffer)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.one_of(st.binary(max_size=300), st.sampled_from(FRAMES)), max_size=12),
       st.integers(min_value=1, max_value=700))
def test_tactile_decoder_never_raises_and_counts_every_rejected_byte(chunks, split):
    stream = b"".join(chunks)
    decoder = tactile.StreamDecoder()
    out = []
    for i in range(0, len(stream), split):  # arbitrary read boundaries
        out += decoder.feed(stream[i:i + split])
    assert accounted(decoder) == len(stream)
    assert len(out) <= sum(1 for c in chunks if c in FRAMES)  # garbage never passes the CRC


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=2000), st.sampled_from(FRAMES))
def test_a_good_frame_after_any_garbage_is_recovered(garbage, frame):
    decoder = tactile.StreamDecoder()
    # A partial frame inside the garbage can hide at most one following frame: send three.
    out = decoder.feed(garbage + frame + frame + frame)
    assert len(out) >= 2
    assert accounted(decoder) == len(garbage) + 3 * len(frame)


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=3000))
def test_board_decoder_never_raises(data):
    decoder = rb.StreamDecoder()
    decoder.feed(data)
    assert accounted(decoder) == len(data)
