"""MCAP files written from wire bytes: stock readers decode them; a cut file is recoverable."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from mcap_ros2.reader import read_ros2_messages
from rosbags.highlevel import AnyReader

from services.recorder.writer import McapRecorder, repair, stamp_ns
from shared import msgs


def tactile(i: int) -> bytes:
    return msgs.serialize(msgs.make(
        "xm_msgs/msg/Tactile", header=msgs.header(100.0 + i * 0.01, "glove_left"), hand="left", rows=16, cols=16,
        pressure=np.full(256, i, np.float32), mask=np.ones(256, np.uint8), sequence=i))


def test_stamp_is_read_from_the_cdr_header():
    assert stamp_ns(tactile(5)) == 100_050_000_000
    assert stamp_ns(b"\x00\x01") is None


def test_both_stock_readers_decode_verbatim_bytes(tmp_path):
    path = tmp_path / "a.mcap"
    rec = McapRecorder(path, {"deployment": "test"})
    for i in range(50):
        rec.write("xm/glove/left/tactile", "xm_msgs/msg/Tactile", tactile(i))
        rec.write("xm/clock", "rosgraph_msgs/msg/Clock",
                  msgs.serialize(msgs.make("rosgraph_msgs/msg/Clock", clock=msgs.stamp(i * 0.01))))
    rec.close()
    seqs = [m.ros_msg.sequence for m in read_ros2_messages(str(path)) if m.channel.topic == "xm/glove/left/tactile"]
    assert seqs == list(range(50))
    with AnyReader([path], default_typestore=msgs.typestore()) as reader:
        conns = {c.topic: c for c in reader.connections}
        assert conns["xm/glove/left/tactile"].msgtype == "xm_msgs/msg/Tactile"
        raws = [raw for c, _, raw in reader.messages(connections=[conns["xm/glove/left/tactile"]])]
        assert raws[7] == tactile(7)  # the wire bytes, unchanged
        assert reader.deserialize(raws[7], "xm_msgs/msg/Tactile").pressure[0] == 7


def test_a_recording_cut_after_a_flush_keeps_what_was_flushed(tmp_path):
    path = tmp_path / "cut.mcap"
    rec = McapRecorder(path, flush_s=1e9)
    for i in range(30):
        rec.write("xm/glove/left/tactile", "xm_msgs/msg/Tactile", tactile(i))
    rec.flush()
    for i in range(30, 40):
        rec.write("xm/glove/left/tactile", "xm_msgs/msg/Tactile", tactile(i))  # lost with the kill below
    cut = tmp_path / "killed.mcap"
    shutil.copy(path, cut)  # the file as a kill -9 leaves it: no footer, no summary
    with pytest.raises(Exception):  # noqa: B017 (a seeking reader needs the footer)
        list(read_ros2_messages(str(cut)))
    fixed = tmp_path / "fixed.mcap"
    assert repair(cut, fixed) == 30
    assert [m.ros_msg.sequence for m in read_ros2_messages(str(fixed))] == list(range(30))
    rec.close()
