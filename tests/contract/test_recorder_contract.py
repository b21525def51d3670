"""Contract of the recorder: a service process seen only through Zenoh, and `xm record`/`xm replay`."""

from __future__ import annotations

import threading
import time

import numpy as np
from mcap.reader import make_reader
from mcap_ros2.reader import read_ros2_messages
from rosbags.highlevel import AnyReader

from services.recorder.cli import record_main, replay_main
from services.recorder.writer import METADATA_NAME, is_complete, read_messages, read_metadata, repair
from shared import msgs
from shared.recording_files import recording_segments
from tests.conftest import (
    Collector,
    ServiceProcess,
    free_endpoint,
    query_json,
    wait_for,
    wait_healthy,
    write_deployment,
)

REC = "xm/recorder/main"
TACTILE = "xm_msgs/msg/Tactile"


def tactile(hand: str, i: int) -> bytes:
    return msgs.serialize(msgs.make(
        TACTILE, header=msgs.header(10.0 + i * 0.01, f"glove_{hand}"), hand=hand, rows=16, cols=16,
        pressure=np.full(256, float(i), np.float32), mask=np.ones(256, np.uint8), sequence=i))


def clock(t: float) -> bytes:
    return msgs.serialize(msgs.make("rosgraph_msgs/msg/Clock", clock=msgs.stamp(t)))


def joints(i: int) -> bytes:
    return msgs.serialize(msgs.make(
        "sensor_msgs/msg/JointState", header=msgs.header(i * 0.01), name=["x", "y"],
        position=np.array([i, -i], float), velocity=np.zeros(2), effort=np.zeros(2)))


def health(session) -> dict:
    return query_json(session, f"{REC}/@health")[0]


def start_recorder(router, tmp_path, **extra) -> tuple[ServiceProcess, object]:
    endpoint, session = router
    params = {"directory": str(tmp_path / "recs"), **extra}
    dep = write_deployment(tmp_path / "d.toml", endpoint, {"recorder": {"main": params}})
    svc = ServiceProcess("recorder", dep, "main", tmp_path / "recorder.log")
    wait_healthy(session, "recorder", "main", svc)
    return svc, session


def test_recorder_stores_typed_messages_verbatim_and_counts_what_it_skips(router, tmp_path):
    svc, session = start_recorder(router, tmp_path)
    try:
        assert health(session)["recording"] is False
        out = tmp_path / "a.mcap"
        started = query_json(session, f"{REC}/@cmd/start", {"path": str(out), "keys": "xm/**"})[0]
        assert started == {"ok": True, "path": str(out)}, svc.output()
        again = query_json(session, f"{REC}/@cmd/start", {})[0]
        assert not again["ok"] and "already recording" in again["error"]
        for i in range(30):
            session.put("xm/glove/left/tactile", tactile("left", i))
            session.put("xm/clock", clock(i * 0.01))
            if i < 10:
                session.put("xm/robot/workcell/state", joints(i))
            if i < 5:
                session.put("xm/glove/right/tactile", b"\x00\x01\x00\x00not cdr")  # malformed
            if i < 7:
                session.put("xm/not/registered", b"anything")
        want = {"xm/glove/left/tactile": 30, "xm/clock": 30, "xm/robot/workcell/state": 10}
        assert wait_for(lambda: health(session)["messages"] == want, 10), (health(session), svc.output())
        report = health(session)
        assert report["recording"] is True and report["path"] == str(out)
        assert report["dropped"]["unregistered_key"] == {"xm/not/registered": 7}
        assert report["dropped"]["bad_payload"] == {"xm/glove/right/tactile": 5}
        status = query_json(session, f"{REC}/@cmd/status")[0]
        assert status["recording"] is True and status["current"]["messages"] == want
        stopped = query_json(session, f"{REC}/@cmd/stop", {})[0]
        assert stopped["ok"] and stopped["path"] == str(out) and stopped["messages"] == want
        assert stopped["bytes"] > 30 * 1000 and stopped["unknown_keys"] == {"xm/not/registered": 7}
        assert stopped["malformed"] == {"xm/glove/right/tactile": 5}
        assert not query_json(session, f"{REC}/@cmd/stop", {})[0]["ok"]
        assert health(session)["recording"] is False and health(session)["last"]["path"] == str(out)

        # the file: verbatim bytes, decodable by both stock readers, no @-keys, metadata
        assert is_complete(out)
        stored = list(read_messages(out))
        assert {s.key for s in stored} == set(want)
        left = "xm/glove/left/tactile"
        assert [s.data for s in stored if s.key == left] == [tactile("left", i) for i in range(30)]
        seqs = [m.ros_msg.sequence for m in read_ros2_messages(str(out)) if m.channel.topic == left]
        assert seqs == list(range(30))
        with AnyReader([out], default_typestore=msgs.typestore()) as reader:
            conn = next(c for c in reader.connections if c.topic == "xm/robot/workcell/state")
            positions = [reader.deserialize(raw, conn.msgtype).position[0]
                         for _, _, raw in reader.messages([conn])]
        assert positions == list(range(10))
        meta = read_metadata(out)[METADATA_NAME]
        assert meta["deployment"] == "test" and meta["keys"] == "xm/**"
        assert meta["recorder"] == "recorder/main" and meta["clock"] == "wall"
    finally:
        assert svc.stop() in (0, -15), svc.output()


def test_recorder_requests_defaults_filters_and_shutdown(router, tmp_path):
    svc, session = start_recorder(router, tmp_path)
    try:
        bad = query_json(session, f"{REC}/@cmd/start", {"keys": "xm//bad"})[0]
        assert not bad["ok"] and "keys" in bad["error"]
        (tmp_path / "taken.mcap").write_bytes(b"keep me")
        taken = query_json(session, f"{REC}/@cmd/start", {"path": str(tmp_path / "taken.mcap")})[0]
        assert not taken["ok"] and "exists" in taken["error"]
        assert (tmp_path / "taken.mcap").read_bytes() == b"keep me"
        # default path in the configured directory; only the requested keys
        started = query_json(session, f"{REC}/@cmd/start", {"path": None, "keys": "xm/clock"})[0]
        assert started["ok"] and started["path"].startswith(str(tmp_path / "recs" / "xm-")), started
        for i in range(20):
            session.put("xm/clock", clock(i))
            session.put("xm/glove/left/tactile", tactile("left", i))
        assert wait_for(lambda: health(session)["messages"] == {"xm/clock": 20}, 10), health(session)
        assert health(session)["messages"].keys() == {"xm/clock"}
        # SIGTERM while recording: the file is closed with its footer
        assert svc.stop() in (0, -15), svc.output()
        assert is_complete(started["path"])
        stamps = [msgs.stamp_seconds(m.ros_msg.clock) for m in read_ros2_messages(started["path"])]
        assert stamps == list(range(20))
    finally:
        svc.stop()


def test_a_recorder_killed_mid_recording_leaves_a_file_readable_up_to_its_last_chunk(router, tmp_path):
    svc, session = start_recorder(router, tmp_path)
    try:
        out = tmp_path / "killed.mcap"
        assert query_json(session, f"{REC}/@cmd/start", {"path": str(out)})[0]["ok"]
        for i in range(50):
            session.put("xm/clock", clock(i))
        # chunks are fsync'ed at least once a second: wait until status says all 50 are on disk
        durable = lambda: query_json(session, f"{REC}/@cmd/status")[0]["current"]["durable_messages"]  # noqa: E731
        assert wait_for(lambda: durable() == 50, 10), svc.output()
        svc.kill()
        assert not is_complete(out)
        got = [msgs.deserialize(s.data, "rosgraph_msgs/msg/Clock").clock.sec for s in read_messages(out)]
        assert got == list(range(50))
        fixed = tmp_path / "fixed.mcap"
        assert repair(out, fixed) == 50
        with AnyReader([fixed], default_typestore=msgs.typestore()) as reader:
            assert sum(1 for _ in reader.messages()) == 50
    finally:
        svc.stop()


def test_kill_9_keeps_every_closed_segment_readable_and_a_restart_repairs_the_open_one(router, tmp_path):
    """Segments of 1 s; the recorder is killed in the fourth. Each closed segment opens in the seeking
    readers (mcap's with its summary and index, rosbags' AnyReader); the restarted recorder repairs
    the cut one in place, and the segments read as one recording of every durable message."""
    svc, session = start_recorder(router, tmp_path, segment_s=1.0)
    try:
        first = tmp_path / "recs" / "seg.mcap"
        assert query_json(session, f"{REC}/@cmd/start", {"path": str(first)})[0]["ok"], svc.output()
        status = lambda: query_json(session, f"{REC}/@cmd/status")[0]["current"]  # noqa: E731
        i = 0
        while len(status()["segments"]) < 4:
            session.put("xm/clock", clock(i))
            i += 1
            time.sleep(0.01)
        assert wait_for(lambda: status()["durable_messages"] == i, 10), svc.output()
        svc.kill()
    finally:
        svc.stop()
    segments = recording_segments(first)
    assert len(segments) >= 4 and not is_complete(segments[-1])
    seen: list[int] = []
    for seg in segments[:-1]:
        with seg.open("rb") as f:
            reader = make_reader(f)
            assert reader.get_summary() is not None
            got = [msgs.deserialize(m.data, "rosgraph_msgs/msg/Clock").clock.sec for _, _, m in reader.iter_messages()]
        with AnyReader([seg], default_typestore=msgs.typestore()) as reader:
            assert len(list(reader.messages())) == len(got)
        seen += got
    assert seen == list(range(len(seen)))
    svc, session = start_recorder(router, tmp_path, segment_s=1.0)
    try:
        assert wait_for(lambda: health(session)["repaired_at_start"], 10), svc.output()
        assert health(session)["repaired_at_start"] == [{"path": str(segments[-1]), "ok": True,
                                                        "messages": i - len(seen)}]
        assert is_complete(segments[-1])
        with AnyReader(segments, default_typestore=msgs.typestore()) as reader:
            got = [msgs.deserialize(raw, "rosgraph_msgs/msg/Clock").clock.sec for _, _, raw in reader.messages()]
        assert got == list(range(i))
        assert [msgs.deserialize(s.data, "rosgraph_msgs/msg/Clock").clock.sec
                for s in read_messages(tmp_path / "recs")] == list(range(i))
    finally:
        svc.stop()


def test_a_recorder_killed_while_recording_resumes_the_recording_in_its_next_segment(router, tmp_path):
    """The restarted recorder goes on with the recording it was killed in (a new segment beside the
    cut one, which it repairs); a stop ends it, and the next start does not resume anything."""
    svc, session = start_recorder(router, tmp_path)
    first = tmp_path / "recs" / "kept.mcap"
    try:
        assert query_json(session, f"{REC}/@cmd/start", {"path": str(first)})[0]["ok"], svc.output()
        for i in range(20):
            session.put("xm/clock", clock(i))
        durable = lambda: query_json(session, f"{REC}/@cmd/status")[0]["current"]["durable_messages"]  # noqa: E731
        assert wait_for(lambda: durable() == 20, 10), svc.output()
        svc.kill()
    finally:
        svc.stop()
    svc, session = start_recorder(router, tmp_path)
    try:
        resumed = health(session)["resumed_at_start"]
        assert resumed and resumed["path"] == str(first) and resumed["segment"] == 1, health(session)
        assert health(session)["recording"] and health(session)["path"] == str(first)
        for i in range(20, 30):
            session.put("xm/clock", clock(i))
        assert wait_for(lambda: health(session)["messages"].get("xm/clock") == 10, 10), health(session)
        stopped = query_json(session, f"{REC}/@cmd/stop")[0]
        assert stopped["ok"] and stopped["segments"] == [str(tmp_path / "recs" / "kept.seg0001.mcap")], stopped
        assert wait_for(lambda: health(session)["repaired_at_start"], 10), svc.output()
        segments = recording_segments(first)
        assert [is_complete(s) for s in segments] == [True, True]
        with AnyReader(segments, default_typestore=msgs.typestore()) as reader:
            got = [msgs.deserialize(raw, "rosgraph_msgs/msg/Clock").clock.sec for _, _, raw in reader.messages()]
        assert got == list(range(30))
        assert not list((tmp_path / "recs").glob(".recording-*"))
    finally:
        assert svc.stop() in (0, -15), svc.output()
    svc, session = start_recorder(router, tmp_path)
    try:
        assert health(session)["resumed_at_start"] is None and not health(session)["recording"]
    finally:
        svc.stop()


def _publish_until(session, stop: threading.Event) -> None:
    i = 0
    while not stop.is_set():
        session.put("xm/clock", clock(i * 0.01))
        if i % 2 == 0:
            session.put("xm/glove/left/tactile", tactile("left", i // 2))
        i += 1
        time.sleep(0.005)  # a live stream at ~200 Hz while `xm record` runs for its set duration


def test_xm_record_then_replay_republishes_the_stored_bytes_in_order(router, tmp_path, capsys):
    endpoint, session = router
    out = tmp_path / "cli.mcap"
    stop = threading.Event()
    publisher = threading.Thread(target=_publish_until, args=(session, stop), daemon=True)
    publisher.start()
    try:
        assert record_main(["--router", endpoint, "--duration", "1.5", "-o", str(out)]) == 0
    finally:
        stop.set()
        publisher.join()
    table = capsys.readouterr().out
    assert "xm/clock" in table and "xm/glove/left/tactile" in table and f"wrote {out}" in table
    recorded = list(read_messages(out))
    n_clock = sum(1 for s in recorded if s.key == "xm/clock")
    assert n_clock >= 10 and {s.key for s in recorded} == {"xm/clock", "xm/glove/left/tactile"}

    got = Collector(session, "xm/**")
    try:
        assert replay_main([str(out), "--router", endpoint, "--rate", "4"]) == 0
        assert wait_for(lambda: len(got.samples) >= len(recorded), 5)
        assert got.samples == [(s.key, s.data) for s in recorded]  # same keys, bytes and order
        got.samples.clear()
        assert replay_main([str(out), "--router", endpoint, "--rate", "10", "--keys", "xm/glove/**"]) == 0
        assert wait_for(lambda: len(got.samples) >= len(recorded) - n_clock, 5)
        assert {k for k, _ in got.samples} == {"xm/glove/left/tactile"}
    finally:
        got.close()


def test_cli_errors_are_clear_and_exit_2(tmp_path, capsys):
    nobody = free_endpoint()
    assert record_main(["--router", nobody, "-o", str(tmp_path / "r.mcap"), "--duration", "1"]) == 2
    assert "no router reachable" in capsys.readouterr().err
    assert replay_main([str(tmp_path / "missing.mcap"), "--router", nobody]) == 2
    assert "no such file" in capsys.readouterr().err
    (tmp_path / "text.mcap").write_text("not a recording")
    assert replay_main([str(tmp_path / "text.mcap"), "--router", nobody]) == 2
    assert "not an MCAP file" in capsys.readouterr().err
    assert record_main(["--deployment", str(tmp_path / "none.toml")]) == 2
    assert "deployment file not found" in capsys.readouterr().err
    (tmp_path / "exists.mcap").write_bytes(b"")
    assert record_main(["--router", nobody, "-o", str(tmp_path / "exists.mcap")]) == 2
    assert "exists" in capsys.readouterr().err


def test_a_recording_starts_with_the_latest_state_published_before_it(router, tmp_path):
    """The world's session label is a state (an ``on_change`` port, cached by its publisher): a
    recording started between two of its messages holds it from its start; a stream's old
    samples (the clock) are not replayed."""
    import zenoh

    from shared.runtime.zsession import declare_publisher

    svc, session = start_recorder(router, tmp_path)
    label = msgs.serialize(msgs.make("xm_msgs/msg/Session", header=msgs.header(3.0), task="assembly", demo=4,
                                     phase="demo", tactile_hand="right", seed_layout="{}"))
    pub = declare_publisher(session, "xm/world/sim/session", zenoh.CongestionControl.DROP, cache_last=True)
    try:
        pub.put(label)
        session.put("xm/clock", clock(1.0))
        out = tmp_path / "s.mcap"
        assert query_json(session, f"{REC}/@cmd/start", {"path": str(out)})[0]["ok"], svc.output()
        assert wait_for(lambda: health(session)["messages"].get("xm/world/sim/session") == 1, 10), health(session)
        session.put("xm/clock", clock(2.0))
        assert wait_for(lambda: health(session)["messages"].get("xm/clock") == 1, 10), health(session)
        assert query_json(session, f"{REC}/@cmd/stop", {})[0]["ok"]
        stored = list(read_messages(out))
        assert [s.data for s in stored if s.key == "xm/world/sim/session"] == [label]
        assert [s.data for s in stored if s.key == "xm/clock"] == [clock(2.0)]
    finally:
        pub.undeclare()
        assert svc.stop() in (0, -15), svc.output()
