"""The dashboard's teaching folders against the real recorder service: a demonstration recorded
from a teaching session lands where the library looks, with its metadata beside it, and reviews;
a panel restarted while it records still stores the outcome at Stop."""

from __future__ import annotations

import json
import threading
from pathlib import Path

import viser

from services.panel import replay
from services.panel.teaching import Teaching
from tests.conftest import free_port, wait_until
from tests.contract.test_recorder_contract import start_recorder
from tests.unit.panel_recordings import scene, session


def test_a_demonstration_recorded_by_the_recorder_service_is_listed_labelled_and_replayable(router, tmp_path):
    """Recorded from one panel, stopped from a restarted one."""
    recorder, zsession = start_recorder(router, tmp_path)
    recs = tmp_path / "recs"

    def ask(verb: str, request: dict) -> list[dict]:
        return [json.loads(r.ok.payload.to_bytes()) for r in
                zsession.get(f"xm/recorder/main/@cmd/{verb}", payload=json.dumps(request), timeout=5.0)
                if r.ok is not None]

    server = viser.ViserServer(host="127.0.0.1", port=free_port(), verbose=False)
    restarted = viser.ViserServer(host="127.0.0.1", port=free_port(), verbose=False)
    errors: list[str] = []
    teaching = Teaching(server, recs, ask, lambda: None, errors.append)
    fresh = Teaching(restarted, recs, ask, lambda: None, errors.append)  # the panel after a restart: no session
    stop = threading.Event()
    scenes = zsession.declare_publisher("xm/recon/main/scene")
    labels = zsession.declare_publisher("xm/world/sim/session")

    def feed() -> None:  # what recon and the world publish, at 20 Hz
        i = 0
        while not stop.wait(0.05):
            scenes.put(scene(i * 0.05, x=0.01 * i))
            labels.put(session(i * 0.05))
            i += 1

    feeder = threading.Thread(target=feed, daemon=True)
    try:
        feeder.start()
        teaching.task.value, teaching.teacher.value, teaching.hand.value = "pick_place", "ada", "left"
        teaching._start_session()
        teaching.next_label.value, teaching.layout.value = "lid on", "cup at the left corner"
        teaching._start_recording()
        assert "recording to" in teaching.record_md.content, teaching.record_md.content
        path = teaching.recording
        assert path is not None and path.parent == recs.resolve()
        teaching.request_scan()
        wait_until(lambda: teaching._scan.done() and teaching.entries, 10, "a scan during the recording")
        assert teaching.entries[0].problems == ["being recorded"]
        wait_until(lambda: (r := ask("status", {})) and r[0]["current"] and
                   r[0]["current"]["messages"].get("xm/recon/main/scene", 0) >= 20, 20, "20 scenes recorded")
        fresh._stop_recording("success")
        assert "saved" in fresh.record_md.content, fresh.record_md.content

        def listed():
            fresh.request_scan()
            fresh._scan.result(10)
            e = fresh.picked()
            return e if e is not None and e.path == path and e.meta.outcome == "success" else None

        entry = wait_until(listed, 20, lambda: f"the demonstration listed with its outcome; library: "
                           f"{fresh.table_md.content}")
        assert entry.trainable and entry.info.duration_s > 0.5 and entry.info.tasks == ["pick_place"]
        meta = json.loads(Path(str(path)[:-len(".mcap")] + ".demo.json").read_text())
        assert (meta["label"], meta["layout"], meta["teacher"], meta["glove_hand"]) == \
            ("lid on", "cup at the left corner", "ada", "left")
        timeline = replay.load_timeline(path)
        assert len(timeline.scene_times) >= 20 and "session" in timeline.frame(timeline.duration)
        assert not errors
    finally:
        stop.set()
        feeder.join(5)
        for t, srv in ((teaching, server), (fresh, restarted)):
            t.close()
            srv.stop()
        assert recorder.stop() in (0, -15), recorder.output()
