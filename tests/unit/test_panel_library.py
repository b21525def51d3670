"""The demonstration library and the review timeline on recordings written by the recorder's writer."""

from __future__ import annotations

import json

import numpy as np
import pytest
from mcap.reader import make_reader

from services.panel import library, replay
from services.panel.library import DemoMeta, Library, MetaError
from services.recorder.writer import McapRecorder
from tests.unit.panel_recordings import write_demo


def test_library_lists_every_recording_with_duration_keys_and_default_metadata(tmp_path):
    write_demo(tmp_path / "a.mcap", seconds=2.0)
    write_demo(tmp_path / "b.mcap", seconds=3.0, keys=("scene", "tactile"))
    (tmp_path / "notes.txt").write_text("not a recording")
    entries = Library(tmp_path).scan(task="pick_place")
    assert [e.name for e in entries] == ["a", "b"]
    a, b = entries
    assert a.info.duration_s == pytest.approx(2.0)
    assert set(a.info.messages) == {"xm/recon/main/scene", "xm/world/sim/session", "xm/glove/right/tactile",
                                    "xm/camhub/cam0/image", "xm/camhub/cam1/image"}
    assert a.info.messages["xm/recon/main/scene"] == 41 and a.info.tasks == ["pick_place"]
    assert a.meta == DemoMeta() and a.trainable and not a.problems
    assert b.info.duration_s == pytest.approx(3.0)
    assert not b.usable and b.problems == ["missing keys: xm/world/sim/session"]
    text = library.table(entries)
    assert "| a | 2.0 | 5 | - | train | unknown |" in text
    assert "- b: **not trainable**: missing keys: xm/world/sim/session" in text


def test_metadata_is_stored_in_a_sidecar_and_the_recording_is_untouched(tmp_path):
    path = write_demo(tmp_path / "demo.mcap")
    before = path.read_bytes()
    lib = Library(tmp_path)
    lib.update(path, label="pour left", split="validation", outcome="success", trim_start_s=0.25, trim_end_s=1.5)
    assert path.read_bytes() == before
    stored = json.loads((tmp_path / "demo.demo.json").read_text())
    assert stored["label"] == "pour left" and stored["split"] == "validation" and stored["trim_end_s"] == 1.5
    entry = lib.scan()[0]
    assert entry.meta.label == "pour left" and entry.usable and not entry.trainable  # validation
    assert entry.meta.window(entry.info.duration_s) == (0.25, 1.5)
    assert "- demo: trimmed to 0.2-1.5 s" in library.table([entry])
    with open(path, "rb") as f:  # a stock MCAP reader still reads the whole file
        assert sum(1 for _ in make_reader(f).iter_messages()) == sum(entry.info.messages.values())


@pytest.mark.parametrize("changes, reason", [
    ({"split": "test"}, "split 'test' is not one of train, validation, excluded"),
    ({"outcome": "great"}, "outcome 'great'"),
    ({"trim_start_s": 1.0, "trim_end_s": 0.5}, "trim_end_s must be null or a number after"),
    ({"trim_start_s": 5.0}, "is not before the end of the recording"),
    ({"trim_start_s": -1.0}, "trim_start_s must be a number >= 0"),
    ({"colour": "red"}, "unknown metadata field(s): colour"),
])
def test_refused_metadata_says_why_and_keeps_the_stored_one(tmp_path, changes, reason):
    path = write_demo(tmp_path / "demo.mcap")
    lib = Library(tmp_path)
    lib.update(path, label="kept")
    with pytest.raises(MetaError, match=reason.replace("(", r"\(").replace(")", r"\)")):
        lib.update(path, **changes)
    assert library.read_meta(path).label == "kept"


def test_bad_recordings_are_listed_with_their_reason(tmp_path):
    write_demo(tmp_path / "cut.mcap", close=False)
    write_demo(tmp_path / "other.mcap", task="assembly")
    (tmp_path / "junk.mcap").write_bytes(b"not an mcap at all")
    write_demo(tmp_path / "badmeta.mcap")
    (tmp_path / "badmeta.demo.json").write_text("{not json")
    live = McapRecorder(tmp_path / "live.mcap")  # a recorder still writing it
    entries = {e.name: e for e in Library(tmp_path).scan(task="pick_place")}
    live.close()
    assert set(entries) == {"badmeta", "cut", "junk", "live", "other"}
    assert entries["live"].problems == ["being recorded"]
    assert any("cut by a crash" in p and "xm record --repair" in p for p in entries["cut"].problems)
    assert entries["cut"].info.messages["xm/recon/main/scene"] > 0  # read up to the cut
    assert entries["other"].problems == ["another task: assembly (the session's is pick_place)"]
    assert entries["junk"].problems[0].startswith("unreadable:") and "MCAP magic" in entries["junk"].problems[0]
    assert entries["badmeta"].problems[0].startswith("metadata: badmeta.demo.json: not readable JSON")
    assert not any(e.trainable for e in entries.values())
    Library(tmp_path).update(tmp_path / "badmeta.mcap", label="fixed")  # an edit replaces the broken sidecar
    assert Library(tmp_path).entry(tmp_path / "badmeta.mcap").usable


def test_a_rescan_reads_only_changed_recordings(tmp_path, monkeypatch):
    write_demo(tmp_path / "a.mcap")
    lib = Library(tmp_path)
    lib.scan()
    reads = []
    monkeypatch.setattr(library, "read_info", lambda p: reads.append(p) or library.RecordingInfo([p]))
    lib.scan()
    assert reads == []
    write_demo(tmp_path / "b.mcap")
    lib.scan()
    assert [p.name for p in reads] == ["b.mcap"]


def test_demo_paths_name_task_and_teacher_and_never_overwrite(tmp_path):
    p = library.next_demo_path(tmp_path, "pick place", "Ada/L", when=0)
    assert p.name.startswith("pick_place-Ada_L-") and p.suffix == ".mcap"
    p.write_bytes(b"")
    assert library.next_demo_path(tmp_path, "pick place", "Ada/L", when=0).name.endswith("-2.mcap")


# --- review --------------------------------------------------------------------------------------

def test_timeline_replays_each_stream_at_the_scrubbed_time(tmp_path):
    tl = replay.load_timeline(write_demo(tmp_path / "demo.mcap", seconds=2.0))
    assert tl.duration == pytest.approx(2.0)
    early, late = tl.frame(0.11), tl.frame(1.91)
    assert {"scene", "session", "tactile/right", "image/cam0", "image/cam1"} <= set(early)
    x_early, x_late = early["scene"].object_keypoints[0], late["scene"].object_keypoints[0]
    assert x_late - x_early == pytest.approx(0.18, abs=1e-4)  # the scene moves 0.2 m over 2 s
    assert isinstance(early["image/cam0"], replay.ImageRef)  # left in the file until shown
    shade = [replay.decode_jpeg(replay.image_bytes({"cam0": f["image/cam0"]})["cam0"]).mean() for f in (early, late)]
    assert shade[1] > shade[0] + 100
    assert float(np.mean(late["tactile/right"].pressure)) > float(np.mean(early["tactile/right"].pressure))
    assert tl.frame(-1.0) == {}


def test_a_segmented_recording_with_a_cut_last_segment_reviews_as_one(tmp_path):
    write_demo(tmp_path / "rec.mcap", seconds=2.0)
    write_demo(tmp_path / "rec.seg0001.mcap", seconds=2.0, offset=2.05, close=False)
    entry = Library(tmp_path).scan()[0]
    assert [p.name for p in entry.info.segments] == ["rec.mcap", "rec.seg0001.mcap"]
    assert entry.info.duration_s == pytest.approx(4.05, abs=0.3)  # the cut segment loses its open chunk
    assert entry.problems[0].startswith("cut by a crash (rec.seg0001.mcap has no footer)")
    tl = replay.load_timeline(tmp_path / "rec.mcap")
    assert tl.duration == pytest.approx(entry.info.duration_s) and "no footer" in replay.marks_text(tl)
    first, second = tl.frame(1.0), tl.frame(tl.duration)
    assert isinstance(first["image/cam1"], replay.ImageRef) and not isinstance(second["image/cam1"], replay.ImageRef)
    jpegs = replay.image_bytes({"a": first["image/cam1"], "b": second["image/cam1"]})
    assert replay.decode_jpeg(jpegs["a"]).mean() < replay.decode_jpeg(jpegs["b"]).mean()
    assert len(tl.scene_times) == len(set(tl.scene_times.tolist())) > 41  # each segment read once


def test_marks_find_unobserved_keypoints_and_lost_glove_frames(tmp_path):
    tl = replay.load_timeline(write_demo(tmp_path / "demo.mcap", masked=(0.5, 1.0), lost=(1.2, 7)))
    masked_t = tl.scene_times[tl.unobserved > 0]
    assert masked_t.min() == pytest.approx(0.5) and masked_t.max() == pytest.approx(0.95)
    assert tl.unobserved.max() == pytest.approx(11 / 42)
    assert [(g.hand, g.lost) for g in tl.gaps] == [("right", 7)] and tl.gaps[0].t == pytest.approx(1.21)
    assert tl.lost_frames() == {"right": 7}
    strip = replay.timeline_strip(tl, cursor=0.0, width=200, height=20)
    red = (strip[:10, :, 0] > 200) & (strip[:10, :, 1] < 200)
    assert red[:, 60].all() and not red[:, 30].any() and not red[:, 150].any()  # 0.6 s in, 0.3 s, 1.5 s
    orange = (strip[10:, :, 0] == 255) & (strip[10:, :, 1] == 150)
    assert orange[:, 121].all() and not orange[:, 60].any()
    text = replay.marks_text(tl)
    assert "keypoints unobserved in 10 of 41 scenes" in text and "right glove lost 7 frames in 1 gaps" in text


def test_signals_hold_each_stream_between_its_messages(tmp_path):
    tl = replay.load_timeline(write_demo(tmp_path / "demo.mcap", seconds=2.0, masked=(0.5, 1.0)))
    t, series = replay.signals(tl, points=201)
    assert t[0] == 0.0 and t[-1] == pytest.approx(2.0)
    assert set(series) == {"keypoints unobserved %", "right glove kPa"}
    unobserved = series["keypoints unobserved %"]
    assert unobserved[70] == pytest.approx(100 * 11 / 42) and unobserved[30] == 0 and unobserved[150] == 0
    kpa = series["right glove kPa"]
    assert kpa[0] == pytest.approx(0.0, abs=0.5) and kpa[-1] == pytest.approx(30.0, abs=0.5)  # ramps 0 -> 30


def test_glove_gaps_count_counter_jumps_and_long_silences_not_jitter():
    t = [0.0, 0.01, 0.02, 0.05, 0.06, 0.5, 0.51]
    gaps = replay.glove_gaps("left", t, [1, 2, 3, 4, 5, 6, 7])
    assert [(g.t, g.lost) for g in gaps] == [(0.5, 0)]  # 30 ms of jitter is no gap; 440 ms of silence is
    gaps = replay.glove_gaps("left", [0.0, 0.01, 0.02], [2**32 - 1, 0, 3])
    assert [g.lost for g in gaps] == [2]  # the counter wraps


def test_playhead_plays_within_the_trim_window_and_steps_between_scenes():
    head = replay.Playhead(start=0.5, end=1.5, position=0.0)
    assert head.position == 0.5
    head.playing, head.speed = True, 2.0
    assert head.advance(0.25) == pytest.approx(1.0)
    assert head.advance(1.0) == 1.5 and not head.playing  # stops at the end of the window
    head.advance(1.0)
    assert head.position == 1.5
    times = [0.0, 0.6, 0.7, 1.2, 1.8]
    head.seek(0.6)
    assert head.step(times, +1) == 0.7 and head.step(times, +1) == 1.2 and head.step(times, +1) == 1.5
    assert head.step(times, -1) == 1.2 and head.step(times, -1) == 0.7
    head.seek(0.6)
    assert head.step(times, -1) == 0.5


def test_camera_grid_tiles_every_camera_and_greys_missing_ones():
    img = np.full((48, 64, 3), 200, np.uint8)
    grid = replay.camera_grid({"cam0": img, "cam2": None}, ["cam0", "cam1", "cam2"], tile=(80, 60), columns=2)
    assert grid.shape == (120, 160, 3)
    assert grid[30:60, 40:80].mean() > 150 and grid[30:60, 120:160].mean() < 100


def test_a_recording_without_drawable_streams_is_refused(tmp_path):
    with pytest.raises(replay.ReplayError, match="no message the review can draw"):
        replay.build_timeline([])
    assert replay.stream_of("xm/glove/left/tactile") == "tactile/left"
    assert replay.stream_of("xm/camhub/cam3/image") == "image/cam3"
    assert replay.stream_of("xm/robot/workcell/state") == "state"
    assert replay.stream_of("xm/clock") is None and replay.stream_of("xm/glove/left/raw") is None
