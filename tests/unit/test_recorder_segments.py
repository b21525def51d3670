"""Recordings in MCAP segments: every closed segment is complete for seeking readers, a crash cuts
only the open one, the repair makes it complete in place, and readers take the segments as one."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

from mcap.reader import make_reader
from rosbags.highlevel import AnyReader

from services.recorder import segments
from services.recorder.segments import SegmentedRecorder, next_segment_index, repair_cut_segments
from services.recorder.writer import is_complete, read_messages
from shared import msgs
from shared.recording_files import recording_segments, segment_path
from tests.conftest import ROOT
from tests.unit.test_recorder_writer import KEY, TACTILE, tactile


def seeking_sequences(path: Path) -> list[int]:
    """Every message of one file through mcap's seeking reader (it reads the summary and index)."""
    with path.open("rb") as f:
        reader = make_reader(f)
        assert reader.get_summary() is not None, f"{path}: no summary section"
        return [msgs.deserialize(m.data, TACTILE).sequence for _, _, m in reader.iter_messages(log_time_order=True)]


def rosbags_sequences(paths: list[Path]) -> list[int]:
    with AnyReader(paths, default_typestore=msgs.typestore()) as reader:
        return [reader.deserialize(raw, TACTILE).sequence for _, _, raw in reader.messages()]


def test_segments_are_named_in_order_and_found_from_any_form(tmp_path):
    first = tmp_path / "xm-20260101-120000.mcap"
    names = [segment_path(first, k) for k in range(12)]
    assert names[1].name == "xm-20260101-120000.seg0001.mcap"
    for p in reversed(names):
        p.write_bytes(b"")
    (tmp_path / "other.mcap").write_bytes(b"")
    assert recording_segments(first) == names
    assert recording_segments(tmp_path) == [tmp_path / "other.mcap"] + names
    assert recording_segments([names[3], names[1]]) == [names[3], names[1]]


def test_segments_rotate_and_each_closed_one_is_complete(tmp_path):
    rec = SegmentedRecorder(tmp_path / "r.mcap", {"deployment": "test"}, segment_s=10.0)
    t0 = rec._opened
    for i in range(30):
        rec.maybe_rotate(t0 + i)  # one message per second of a 10 s segment
        rec.write(KEY, TACTILE, tactile(i))
    summary = rec.close()
    assert [p.name for p in rec.segments] == ["r.mcap", "r.seg0001.mcap", "r.seg0002.mcap"]
    assert all(is_complete(p) for p in rec.segments)
    assert [seeking_sequences(p) for p in rec.segments] == [list(range(0, 10)), list(range(10, 20)),
                                                            list(range(20, 30))]
    assert summary.messages == {KEY: 30} and summary.durable == 30
    assert [msgs.deserialize(s.data, TACTILE).sequence for s in read_messages(tmp_path / "r.mcap")] == list(range(30))
    assert rosbags_sequences(recording_segments(tmp_path)) == list(range(30))


def test_each_rotation_hands_the_closed_segments_memory_back(tmp_path, monkeypatch):
    trims = []
    monkeypatch.setattr(segments, "trim_heap", lambda: trims.append(1) or True)
    rec = SegmentedRecorder(tmp_path / "r.mcap", {"deployment": "test"}, segment_s=10.0)
    t0 = rec._opened
    for i in range(25):
        rec.maybe_rotate(t0 + i)
        rec.write(KEY, TACTILE, tactile(i))
    rec.close()
    assert len(trims) == 2  # two segments closed by rotation


def test_trimming_the_heap_gives_freed_pages_back_on_glibc():
    def rss_mb() -> float:
        return int(Path("/proc/self/statm").read_text().split()[1]) * 4096 / 1e6

    blocks = [bytearray(100_000) for _ in range(1000)]  # 100 MB in heap blocks under glibc's mmap threshold...
    kept = blocks[::50]  # ...of which a few stay alive, so the heap cannot shrink from its top
    del blocks
    before = rss_mb()
    assert segments.trim_heap()
    assert rss_mb() < before - 50, (before, rss_mb())
    assert len(kept) == 20


def test_kill_9_leaves_closed_segments_readable_and_the_repair_completes_the_open_one(tmp_path):
    path = tmp_path / "killed.mcap"
    script = textwrap.dedent(f"""
        import os, sys, time
        sys.path.insert(0, {str(ROOT)!r})
        from services.recorder.segments import SegmentedRecorder
        from tests.unit.test_recorder_writer import tactile
        rec = SegmentedRecorder({str(path)!r}, {{"deployment": "kill"}}, segment_s=0.2, flush_s=0.05)
        for i in range(130):
            rec.write("{KEY}", "{TACTILE}", tactile(i))
            time.sleep(0.01)
        rec.flush()
        os.kill(os.getpid(), 9)  # no close(): the open segment keeps no summary and no footer
    """)
    subprocess.run([sys.executable, "-c", script], cwd=ROOT, check=False, timeout=60)
    segments = recording_segments(path)
    assert len(segments) >= 3 and len(segments[0].read_bytes()) > 0
    closed, cut = segments[:-1], segments[-1]
    assert all(is_complete(p) for p in closed) and not is_complete(cut)
    seen: list[int] = []
    for p in closed:  # every closed segment on its own, through both seeking readers
        got = seeking_sequences(p)
        assert got == rosbags_sequences([p])
        seen += got
    assert seen == list(range(len(seen)))
    everything = [msgs.deserialize(s.data, TACTILE).sequence for s in read_messages(path)]
    assert everything == list(range(130)), "the cut segment streams up to its flushed end"
    reports = repair_cut_segments(tmp_path)
    assert reports == [{"path": str(cut), "ok": True, "messages": 130 - len(seen)}]
    assert is_complete(cut) and seeking_sequences(cut) == list(range(len(seen), 130))
    assert rosbags_sequences(segments) == list(range(130))
    assert repair_cut_segments(tmp_path) == []  # nothing left to repair


def test_a_segment_being_written_is_not_repaired(tmp_path):
    rec = SegmentedRecorder(tmp_path / "live.mcap", segment_s=60.0)
    rec.write(KEY, TACTILE, tactile(0))
    rec.flush()
    assert not is_complete(rec.path)
    assert repair_cut_segments(tmp_path) == []
    rec.close()
    assert is_complete(rec.path)


def test_a_resumed_recording_goes_on_after_its_last_segment(tmp_path):
    first = tmp_path / "r.mcap"
    assert next_segment_index(first) == 0
    rec = SegmentedRecorder(first, segment_s=0)
    rec.write(KEY, TACTILE, tactile(0))
    rec.close()
    assert next_segment_index(first) == 1
    resumed = SegmentedRecorder(first, segment_s=10.0, first_index=next_segment_index(first))
    resumed.write(KEY, TACTILE, tactile(1))
    assert resumed.maybe_rotate(now=resumed._opened + 10.0)  # the next one after the resumed segment
    resumed.write(KEY, TACTILE, tactile(2))
    resumed.close()
    assert [p.name for p in resumed.segments] == ["r.seg0001.mcap", "r.seg0002.mcap"]
    assert rosbags_sequences(recording_segments(first)) == [0, 1, 2]
    assert next_segment_index(first) == 3
