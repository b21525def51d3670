"""The recorder spare's buffer (services/recorder/spare_buffer.py) and where a cut recording ends
(services/recorder/spare.py ``recording_cut``)."""

from __future__ import annotations

import shutil

from services.recorder.segments import SegmentedRecorder
from services.recorder.spare import recording_cut
from services.recorder.spare_buffer import ENTRY_OVERHEAD, Cut, Overlap, SpareBuffer, after_cut, overlaps
from shared import msgs

S = 1_000_000_000


def test_the_buffer_keeps_the_last_seconds_in_order_and_never_grows_past_its_bounds():
    buf = SpareBuffer(seconds=2.0, max_bytes=1 << 30)
    for i in range(1000):  # 10 s at 100 Hz
        buf.add("xm/a", b"x" * 10, i * S // 100)
    held = buf.freeze()
    assert [t for _, _, t in held] == [i * S // 100 for i in range(799, 1000)]  # the newest 2 s
    assert buf.dropped == 799 and len(buf) == 201
    assert buf.span_s() == 2.0
    buf.add("xm/a", b"late", 11 * S)  # frozen: nothing more is taken
    assert len(buf) == 201

    small = SpareBuffer(seconds=60.0, max_bytes=10 * (1000 + len("xm/a") + ENTRY_OVERHEAD))
    for i in range(100_000):
        small.add("xm/a", i.to_bytes(4, "little") * 250, i)
        assert small.bytes <= small.max_bytes and len(small) <= 10
    assert [int.from_bytes(p[:4], "little") for _, p, _ in small.freeze()] == list(range(99_990, 100_000))
    huge = SpareBuffer(seconds=60.0, max_bytes=100)
    huge.add("xm/a", b"y" * 1000, 1)  # one payload over the cap is not kept
    assert len(huge) == 0 and huge.bytes == 0


def test_since_returns_the_entries_from_a_time_on():
    buf = SpareBuffer(seconds=10.0)
    for i in range(10):
        buf.add("xm/a", bytes([i]), i * S)
    assert [p for _, p, _ in buf.since(7 * S)] == [b"\x07", b"\x08", b"\x09"]
    assert buf.since(11 * S) == []


def entries(*spec: tuple[str, int, float]) -> list[tuple[str, bytes, int]]:
    return [(key, f"{key}:{n}".encode(), int(t * S)) for key, n, t in spec]


def test_after_the_cut_by_the_last_kept_payload_or_else_by_time_and_only_keys_taken():
    buf = entries(("xm/a", 1, 1.0), ("xm/b", 1, 1.05), ("xm/b", 2, 1.11), ("xm/c", 1, 1.12), ("xm/a", 2, 1.14),
                  ("xm/a", 3, 1.2), ("xm/b", 3, 1.25), ("xm/x/@h", 1, 1.26), ("xm/a", 4, 1.3))
    # the killed recorder kept xm/a:2 (received at 1.13 s there, at 1.14 s here) and xm/b:1, not
    # xm/b:2 (received at 1.11 s here, after its cut there); its last kept message came at 1.13 s
    cut = Cut(int(1.13 * S), {"xm/a": (b"xm/a:2", int(1.13 * S)), "xm/b": (b"xm/b:1", int(1.06 * S))})
    got = after_cut(buf, cut, lambda key: key.startswith("xm/") and "@" not in key and key != "xm/c")
    assert [p for _, p, _ in got] == [b"xm/b:2", b"xm/a:3", b"xm/b:3", b"xm/a:4"]
    # by time alone, for keys whose last kept message the buffer does not hold
    assert [p for _, p, _ in after_cut(buf, Cut(int(1.13 * S)), lambda key: True)] == [
        b"xm/a:2", b"xm/a:3", b"xm/b:3", b"xm/x/@h:1", b"xm/a:4"]
    # an identical payload far from the kept one's time is another message: by time then
    repeat = [("xm/s", b"same", 0), ("xm/s", b"same", 5 * S), ("xm/s", b"same", 9 * S)]
    kept = Cut(int(5 * S), {"xm/s": (b"same", 5 * S)})
    assert after_cut(repeat, kept, lambda key: True) == [("xm/s", b"same", 9 * S)]
    assert after_cut(repeat, Cut(10 * S, {"xm/s": (b"same", 10 * S)}), lambda key: True) == []
    assert after_cut([], cut, lambda key: True) == []


def test_live_copies_of_what_the_buffer_wrote_are_recognised_in_order_once():
    written = entries(("xm/a", 1, 1.0), ("xm/a", 2, 2.0), ("xm/a", 3, 2.1), ("xm/b", 1, 2.05), ("xm/s", 1, 0.5))
    overlap = Overlap(written, int(2.0 * S), lambda key: key == "xm/s")
    assert overlap
    # the live subscription started after xm/a:2 reached the spare: its first message is xm/a:3
    assert overlap.is_copy("xm/a", b"xm/a:3")
    assert not overlap.is_copy("xm/a", b"xm/a:3")  # a second xm/a:3 is a new message
    assert not overlap.is_copy("xm/a", b"xm/a:1")  # received before the live subscription: not a copy
    assert not overlap.is_copy("xm/b", b"xm/b:2")  # xm/b goes on past the buffer: it expects nothing more
    assert not overlap.is_copy("xm/b", b"xm/b:1")
    assert overlap.is_copy("xm/s", b"xm/s:1")  # a state's subscription starts with its latest message
    assert not overlap
    assert not Overlap([], 0, lambda key: True)


def test_overlap_needs_one_message_in_both():
    buf = entries(("xm/a", 1, 1.0), ("xm/a", 2, 1.1))
    assert overlaps(buf, entries(("xm/a", 2, 1.2), ("xm/a", 3, 1.3)))
    assert not overlaps(buf, entries(("xm/a", 3, 1.3)))
    assert not overlaps([], entries(("xm/a", 3, 1.3)))


def clock(i: int) -> bytes:
    return msgs.serialize(msgs.make("rosgraph_msgs/msg/Clock", clock=msgs.stamp(float(i))))


def test_recording_cut_reads_the_last_whole_chunk_of_a_cut_segment(tmp_path):
    path = tmp_path / "r.mcap"
    rec = SegmentedRecorder(path, {}, segment_s=0, flush_s=1000.0)
    for i in range(30):
        rec.write("xm/clock", "rosgraph_msgs/msg/Clock", clock(i), (100 + i) * S)
        if i < 3:
            rec.write("xm/other", "rosgraph_msgs/msg/Clock", clock(1000 + i), (100 + i) * S + 1)
        if i in (9, 19):
            rec.flush()  # whole chunks end after messages 9 and 19; 20-29 are in the open one
    cut_copy = tmp_path / "cut.mcap"
    shutil.copyfile(path, cut_copy)  # as a kill -9 leaves it: no footer, the open chunk lost
    with cut_copy.open("r+b") as f:  # and a torn tail of a chunk being written
        f.seek(0, 2)
        f.write(b"\x06" + (10_000).to_bytes(8, "little") + b"torn")
    rec.close()
    cut = recording_cut(cut_copy, 1)
    assert cut.time_ns == 119 * S
    assert cut.last == {"xm/clock": (clock(19), 119 * S)}  # its channel is found in the first chunk
    assert recording_cut(path, 1).time_ns == 129 * S  # a complete segment: its last chunk
    assert recording_cut(tmp_path / "none.mcap", 1) is None
    empty = SegmentedRecorder(tmp_path / "e.mcap", {}, segment_s=0)  # killed before its first chunk
    started = int(empty.current.metadata["started_ns"])
    assert recording_cut(tmp_path / "e.mcap", 1) == Cut(started)
    empty.close()
