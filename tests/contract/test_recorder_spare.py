"""A recorder's standby spare listens while it waits: killed mid-recording, the recorder's takeover
leaves no gap in the recording, and no message twice."""

from __future__ import annotations

import itertools
import os
import signal
import subprocess
import sys
import threading
import time

from mcap.reader import make_reader

from shared import msgs
from shared.recording_files import recording_segments
from shared.runtime.service import STANDBY_READY
from tests.conftest import ROOT, ServiceProcess, query_json, wait_for, wait_healthy, write_deployment

REC = "xm/recorder/main"
RATE_HZ = 50.0


def clock(i: int) -> bytes:
    return msgs.serialize(msgs.make("rosgraph_msgs/msg/Clock", clock=msgs.stamp(float(i))))


class Publisher:
    """``xm/clock`` at a steady rate, each message's ``sec`` its sequence number."""

    def __init__(self, session) -> None:
        self.session, self.sent = session, 0
        self.longest_pause = 0.0  # the publisher's own largest interval (s): a starved host stretches it
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        next_at = last = time.monotonic()
        while not self._stop.is_set():
            self.session.put("xm/clock", clock(self.sent))
            now = time.monotonic()
            self.longest_pause, last = max(self.longest_pause, now - last), now
            self.sent += 1
            next_at += 1 / RATE_HZ
            self._stop.wait(max(0.0, next_at - time.monotonic()))  # the publisher's pace

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()


class Spare:
    """``python -m services.recorder --standby``, started by ``go`` on its stdin as the supervisor does."""

    def __init__(self, deployment, log) -> None:
        self.log = log
        self._log = log.open("w")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "services.recorder", "--deployment", str(deployment), "--instance", "main",
             "--standby"], cwd=ROOT, stdin=subprocess.PIPE, stdout=self._log, stderr=subprocess.STDOUT,
            start_new_session=True)

    def go(self) -> None:
        self.proc.stdin.write(b"go\n")
        self.proc.stdin.flush()

    def stop(self) -> int:
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGTERM)
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait()
        self._log.close()
        return self.proc.returncode


def test_a_listening_spare_takes_over_a_recording_without_a_gap_or_a_duplicate(router, tmp_path):
    endpoint, session = router
    dep = write_deployment(tmp_path / "d.toml", endpoint, {"recorder": {"main": {"directory": str(tmp_path / "recs")}}})
    recorder = ServiceProcess("recorder", dep, "main", tmp_path / "recorder.log")
    spare = Spare(dep, tmp_path / "spare.log")
    health = lambda: query_json(session, f"{REC}/@health")  # noqa: E731
    first = tmp_path / "recs" / "run.mcap"
    publisher = None
    try:
        wait_healthy(session, "recorder", "main", recorder)
        assert wait_for(lambda: STANDBY_READY in spare.log.read_text(), 60), spare.log.read_text()
        publisher = Publisher(session)
        assert query_json(session, f"{REC}/@cmd/start", {"path": str(first)})[0]["ok"], recorder.output()
        status = lambda: query_json(session, f"{REC}/@cmd/status")[0]["current"]  # noqa: E731
        assert wait_for(lambda: status()["durable_messages"] >= 50, 20), recorder.output()
        recorder.kill()  # SIGKILL mid-recording: up to a flush period of received messages is not on disk
        killed_at = publisher.sent
        # the supervisor's reaction to the death: without the buffer, this much would be missing
        assert wait_for(lambda: publisher.sent >= killed_at + RATE_HZ / 2, 10, period=0.02)
        spare.go()
        took = wait_for(lambda: (h := health()) and h[0]["pid"] == spare.proc.pid
                        and (h[0]["spare_buffer"] or {}).get("written") and h[0], 30)
        assert took, (spare.log.read_text(), health())
        assert took["resumed_at_start"]["path"] == str(first), took
        report = took["spare_buffer"]
        assert report["messages_held"] >= report["written"] > RATE_HZ / 2, report
        assert wait_for(lambda: health()[0]["messages"].get("xm/clock", 0) >= report["written"] + RATE_HZ, 20)
        publisher.stop()
        final = publisher.sent
        assert wait_for(lambda: health()[0]["repaired_at_start"], 20), spare.log.read_text()
        # the recording takes in what is still in flight before it stops (what it lacks is checked below)
        segments = recording_segments(first)
        kept = lambda: len(_clock_messages(segments[:-1]))  # noqa: E731  (the repaired segments)
        before = min(seq for _, seq in _clock_messages(segments[:1]))  # published before the recording began
        wait_for(lambda: kept() + health()[0]["messages"].get("xm/clock", 0) >= final - before, 10)
        stopped = query_json(session, f"{REC}/@cmd/stop")[0]
        assert stopped["ok"], stopped
    finally:
        if publisher is not None:
            publisher.stop()
        recorder.stop()
        spare_rc = spare.stop()
    assert spare_rc in (0, -15), spare.log.read_text()

    segments = recording_segments(first)
    assert len(segments) == 2, segments
    got = _clock_messages(segments)
    seqs = [seq for _, seq in got]
    assert len(seqs) == len(set(seqs)), f"{len(seqs) - len(set(seqs))} messages recorded twice"
    missing = sorted(set(range(min(seqs), final)) - set(seqs))  # from the recording's start on
    assert not missing, (f"{len(missing)} missing: {missing[:20]}; killed at {killed_at}, "
                         f"{len(_clock_messages(segments[:-1]))} in the cut segments; {report}")
    times = sorted(t for t, _ in got)
    gap, at = max((b - a, a) for a, b in itertools.pairwise(times))
    # the handover took >= 0.5 s; the buffer bridges it, leaving the publisher's own pauses and jitter
    assert gap < (publisher.longest_pause + 0.25) * 1e9, (
        f"largest gap between recorded messages: {gap * 1e-9:.3f} s, {(at - report['cut_ns']) * 1e-9:+.3f} s "
        f"from the cut (the publisher's longest pause {publisher.longest_pause:.3f} s); {report}")


def _clock_messages(segments) -> list[tuple[int, int]]:
    """(log time, sequence number) of every ``xm/clock`` message, read with the stock ``mcap`` reader."""
    out = []
    for path in segments:
        with open(path, "rb") as f:
            for _, _, message in make_reader(f).iter_messages(topics=["xm/clock"]):
                out.append((message.log_time, msgs.deserialize(message.data, "rosgraph_msgs/msg/Clock").clock.sec))
    return out
