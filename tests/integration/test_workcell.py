"""The whole simulated workcell through the supervisor: record, read back with stock readers,
kill -9 a service and see it come back. The recorded rates against the nominal ones: bench/workcell.py."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from collections import defaultdict

import pytest
from mcap_ros2.reader import read_ros2_messages
from rosbags.highlevel import AnyReader

from shared import keys
from shared.msgs import typestore
from tests.conftest import ROOT, query_router, sim_workcell, wait_until

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def workcell(tmp_path_factory):
    with sim_workcell(tmp_path_factory.mktemp("workcell")) as cell:
        yield cell


def stamp_of(ros_msg) -> float:
    """The header stamp, or a Clock message's time (in the deployment's time base: sim time)."""
    header = getattr(ros_msg, "header", None)
    t = header.stamp if header is not None else ros_msg.clock
    return t.sec + t.nanosec * 1e-9


def record(workcell, seconds: float, name: str):
    out = workcell["tmp"] / name
    subprocess.run([sys.executable, "-m", "shared.cli", "record", "--deployment", str(workcell["deployment"]),
                    "--duration", str(seconds), "-o", str(out)], cwd=ROOT, check=True, timeout=60 + seconds)
    return out


def test_recording_decodes_with_stock_readers_every_key_in_order(workcell):
    out = record(workcell, 10, "ten_seconds.mcap")
    stamps: dict[str, list[float]] = defaultdict(list)
    for m in read_ros2_messages(str(out)):
        stamps[m.channel.topic].append(stamp_of(m.ros_msg))
    rosbags_counts: dict[str, int] = defaultdict(int)
    with AnyReader([out], default_typestore=typestore()) as reader:
        for conn, _, raw in reader.messages():
            reader.deserialize(raw, conn.msgtype)
            rosbags_counts[conn.topic] += 1
    problems = []
    for spec in keys.REGISTRY:
        ts = stamps.get(spec.key, [])
        if rosbags_counts.get(spec.key, 0) != len(ts):
            problems.append(f"{spec.key}: rosbags read {rosbags_counts.get(spec.key, 0)}, mcap_ros2 {len(ts)}")
        if len(ts) < 3:
            problems.append(f"{spec.key}: only {len(ts)} messages")
        elif ts != sorted(ts) or ts[-1] <= ts[0]:
            problems.append(f"{spec.key}: stamps out of order or not advancing: {ts[:5]} ... {ts[-5:]}")
    assert not problems, "\n".join(problems)


def test_killed_service_is_restarted_and_publishes_again(workcell):
    router = workcell["router"]

    def recon() -> dict | None:
        sup = next(iter(query_router(router, "xm/deploy/supervisor/@health")), None)
        return next((c for c in sup["children"] if c["service"] == "recon"), None) if sup else None

    child = recon()
    os.kill(child["pid"], signal.SIGKILL)

    def restarted_and_publishing() -> bool:
        now = recon()
        if not (now and now["restarts"] >= 1 and now["pid"] and now["pid"] != child["pid"]):
            return False
        health = query_router(router, "xm/recon/main/@health")
        return bool(health) and health[0]["published_hz"].get("xm/recon/main/scene", 0) > 0

    wait_until(restarted_and_publishing, 30, lambda: f"recon restarted and publishing: {recon()}", period=1.0)


def test_status_lists_every_service(workcell):
    out = subprocess.run([sys.executable, "-m", "shared.cli", "status", str(workcell["deployment"])],
                         cwd=ROOT, capture_output=True, text=True, timeout=30)
    assert out.returncode == 0, out.stderr
    for svc in ("world", "glove/left", "glove/right", "camhub", "recon", "policy", "trajopt", "robot", "panel"):
        assert svc in out.stdout
