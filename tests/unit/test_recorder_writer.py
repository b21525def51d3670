"""MCAP files written from wire bytes: stock readers decode them; a cut file stays readable."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from mcap_ros2.reader import read_ros2_messages
from rosbags.highlevel import AnyReader

from services.recorder.cli import record_main, summary_table
from services.recorder.writer import (
    METADATA_NAME,
    SUMMARY_NAME,
    McapRecorder,
    RecordingError,
    check_mcap,
    check_payload,
    is_complete,
    read_messages,
    read_metadata,
    repair,
    stamp_ns,
)
from shared import msgs
from tests.conftest import ROOT

TACTILE = "xm_msgs/msg/Tactile"
KEY = "xm/glove/left/tactile"


def tactile(i: int) -> bytes:
    return msgs.serialize(msgs.make(
        TACTILE, header=msgs.header(100.0 + i * 0.01, "glove_left"), hand="left", rows=16, cols=16,
        pressure=np.full(256, i, np.float32), mask=np.ones(256, np.uint8), sequence=i))


def clock(t: float) -> bytes:
    return msgs.serialize(msgs.make("rosgraph_msgs/msg/Clock", clock=msgs.stamp(t)))


def seqs_rosbags(path) -> list[int]:
    with AnyReader([path], default_typestore=msgs.typestore()) as reader:
        conns = [c for c in reader.connections if c.topic == KEY]
        return [reader.deserialize(raw, TACTILE).sequence for _, _, raw in reader.messages(connections=conns)]


def test_stamp_comes_from_the_header_or_the_clock_field():
    assert check_payload(TACTILE, tactile(5)) == 100_050_000_000
    assert check_payload("rosgraph_msgs/msg/Clock", clock(2.5)) == 2_500_000_000
    assert stamp_ns(msgs.make("std_msgs/msg/String", data="no stamp")) is None
    with pytest.raises(msgs.MessageError):
        check_payload(TACTILE, b"\x00\x01\x00\x00garbage")


def test_both_stock_readers_decode_verbatim_bytes_and_times(tmp_path):
    path = tmp_path / "a.mcap"
    rec = McapRecorder(path, {"deployment": "test", "keys": "xm/**"})
    for i in range(50):
        t = 1_000_000_000 + i * 10_000_000
        rec.write(KEY, TACTILE, tactile(i), log_time_ns=t)
        rec.write("xm/clock", "rosgraph_msgs/msg/Clock", clock(i * 0.01), log_time_ns=t)
    summary = rec.close()
    assert summary.messages == {KEY: 50, "xm/clock": 50}
    assert summary.rates_hz[KEY] == pytest.approx(100.0)
    got = [m for m in read_ros2_messages(str(path)) if m.channel.topic == KEY]
    assert [m.ros_msg.sequence for m in got] == list(range(50))
    assert got[3].ros_msg.pressure[0] == 3
    assert got[3].schema.name == TACTILE and got[3].schema.encoding == "ros2msg"
    assert got[3].channel.message_encoding == "cdr"
    assert got[3].log_time_ns == 1_030_000_000 and got[3].sequence_count == 3  # receive time, per-key counter
    assert got[3].publish_time_ns == 100_030_000_000  # header stamp
    with AnyReader([path], default_typestore=msgs.typestore()) as reader:
        conns = {c.topic: c for c in reader.connections}
        assert conns[KEY].msgtype == TACTILE
        raws = [raw for _, _, raw in reader.messages(connections=[conns[KEY]])]
        assert raws[7] == tactile(7)  # the wire bytes, unchanged
        assert reader.deserialize(raws[7], TACTILE).pressure[0] == 7
        clocks = [reader.deserialize(raw, "rosgraph_msgs/msg/Clock").clock.nanosec
                  for _, _, raw in reader.messages(connections=[conns["xm/clock"]])]
        assert clocks[:3] == [0, 10_000_000, 20_000_000]
    meta = read_metadata(path)
    assert meta[METADATA_NAME]["deployment"] == "test" and meta[METADATA_NAME]["keys"] == "xm/**"
    assert json.loads(meta[SUMMARY_NAME]["messages"]) == {KEY: 50, "xm/clock": 50}


def test_malformed_payload_is_refused_and_the_file_stays_decodable(tmp_path):
    path = tmp_path / "m.mcap"
    rec = McapRecorder(path)
    rec.write(KEY, TACTILE, tactile(0))
    with pytest.raises(msgs.MessageError):
        rec.write(KEY, TACTILE, b"\x00\x01\x00\x00\xff")
    rec.write(KEY, TACTILE, tactile(1))
    assert rec.close().messages == {KEY: 2}
    assert [m.ros_msg.sequence for m in read_ros2_messages(str(path))] == [0, 1]
    with pytest.raises(RecordingError):
        rec.write(KEY, TACTILE, tactile(2))


def test_a_recording_cut_after_a_flush_keeps_what_was_flushed(tmp_path):
    path = tmp_path / "cut.mcap"
    rec = McapRecorder(path, {"deployment": "test"}, flush_s=1e9)
    for i in range(30):
        rec.write(KEY, TACTILE, tactile(i))
    rec.flush()
    for i in range(30, 40):
        rec.write(KEY, TACTILE, tactile(i))  # still in the open chunk: lost with the kill below
    cut = tmp_path / "killed.mcap"
    cut.write_bytes(path.read_bytes())  # the file as a kill -9 leaves it: no summary, no footer
    rec.close()
    assert not is_complete(cut) and is_complete(path)
    with pytest.raises(Exception):  # noqa: B017 (seeking readers need the footer)
        list(read_ros2_messages(str(cut)))
    notes: list[str] = []
    stored = list(read_messages(cut, cut=notes))
    assert [msgs.deserialize(s.data, TACTILE).sequence for s in stored] == list(range(30))
    assert stored[0].key == KEY and stored[0].msgtype == TACTILE and "--repair" in notes[0]
    assert read_metadata(cut)[METADATA_NAME]["deployment"] == "test"
    fixed = tmp_path / "fixed.mcap"
    assert repair(cut, fixed) == 30
    assert [m.ros_msg.sequence for m in read_ros2_messages(str(fixed))] == list(range(30))
    assert seqs_rosbags(fixed) == list(range(30))
    assert read_metadata(fixed)[METADATA_NAME]["repaired_from"] == str(cut)


def test_full_chunks_reach_the_disk_without_an_explicit_flush(tmp_path):
    path = tmp_path / "chunks.mcap"
    rec = McapRecorder(path, flush_s=1e9, chunk_bytes=8 * 1024)
    for i in range(60):
        rec.write(KEY, TACTILE, tactile(i))
    assert rec.chunks >= 5
    prefix = path.read_bytes()  # what is on disk right now, as a kill would leave it
    rec.close()
    cut = tmp_path / "prefix.mcap"
    cut.write_bytes(prefix)
    got = [msgs.deserialize(s.data, TACTILE).sequence for s in read_messages(cut)]
    assert len(got) >= 50 and got == list(range(len(got)))


def test_any_prefix_of_a_recording_reads_as_a_prefix_of_its_messages(tmp_path):
    path = tmp_path / "full.mcap"
    rec = McapRecorder(path, chunk_bytes=4 * 1024)
    for i in range(40):
        rec.write(KEY, TACTILE, tactile(i))
    rec.close()
    data = path.read_bytes()
    previous = 0
    for length in range(8, len(data), max(1, len(data) // 37)):
        (tmp_path / "p.mcap").write_bytes(data[:length])
        got = [msgs.deserialize(s.data, TACTILE).sequence for s in read_messages(tmp_path / "p.mcap")]
        assert got == list(range(len(got)))
        assert len(got) >= previous
        previous = len(got)
    assert previous >= 30


def test_a_process_killed_mid_recording_leaves_a_readable_file(tmp_path):
    path = tmp_path / "killed.mcap"
    script = textwrap.dedent(f"""
        import os, sys, time
        sys.path.insert(0, {str(ROOT)!r})
        from services.recorder.writer import McapRecorder
        from tests.unit.test_recorder_writer import tactile
        rec = McapRecorder({str(path)!r}, {{"deployment": "kill"}}, flush_s=0.05)
        for i in range(200):
            rec.write("{KEY}", "{TACTILE}", tactile(i))
            if i == 120:
                time.sleep(0.1)  # flush_s is a time: once it has passed, the next write flushes 0..120
        os._exit(9)  # no close(): no summary, no footer
    """)
    subprocess.run([sys.executable, "-c", script], cwd=ROOT, check=False, timeout=60)
    assert path.exists() and not is_complete(path)
    got = [msgs.deserialize(s.data, TACTILE).sequence for s in read_messages(path)]
    assert len(got) >= 121 and got == list(range(len(got)))
    fixed = tmp_path / "fixed.mcap"
    assert record_main(["--repair", str(path), "-o", str(fixed)]) == 0
    assert seqs_rosbags(fixed) == got
    assert record_main(["--repair", str(path), "-o", str(fixed)]) == 2  # never overwrites


def test_files_that_are_not_recordings_are_named_as_such(tmp_path):
    with pytest.raises(RecordingError, match="no such file"):
        check_mcap(tmp_path / "missing.mcap")
    (tmp_path / "x.mcap").write_text("hello")
    with pytest.raises(RecordingError, match="not an MCAP file"):
        check_mcap(tmp_path / "x.mcap")
    with pytest.raises(RecordingError, match="directory"):
        check_mcap(tmp_path)
    with pytest.raises(RecordingError):
        repair(tmp_path / "x.mcap", tmp_path / "y.mcap")


def test_summary_table_lists_keys_rates_and_skipped_keys():
    text = summary_table({"path": "r.mcap", "messages": {KEY: 200, "xm/clock": 100}, "bytes": 2_000_000,
                          "seconds": 2.0, "rates_hz": {KEY: 100.0, "xm/clock": 50.0},
                          "unknown_keys": {"xm/odd": 3}, "malformed": {}})
    lines = text.splitlines()
    assert lines[1].split() == ["xm/clock", "100", "50.0"] and lines[2].split() == [KEY, "200", "100.0"]
    assert "xm/odd" in text and "not in the key registry" in text and "300 messages" in lines[-1]
