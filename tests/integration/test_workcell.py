"""The whole simulated workcell through the supervisor: record, read back with stock readers,
kill -9 a service and see it come back."""

from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest

from shared import keys

ROOT = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.slow


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def query(router: str, selector: str, timeout: float = 3.0) -> list[dict]:
    import zenoh

    from shared.runtime import open_client

    try:
        session = open_client(router)
    except zenoh.ZError:  # router not up yet
        return []
    try:
        return [json.loads(r.ok.payload.to_bytes()) for r in session.get(selector, timeout=timeout) if r.ok]
    finally:
        session.close()


@pytest.fixture(scope="module")
def workcell(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("workcell")
    text = (ROOT / "deploy/sim.toml").read_text()
    router = f"tcp/127.0.0.1:{free_port()}"
    text = re.sub(r'router = "[^"]*"', f'router = "{router}"', text)
    text = re.sub(r'run_dir = "[^"]*"', f'run_dir = "{tmp}/run"', text)
    # The same cell whether or not this checkout has trained a policy: the naive fallback (the
    # learned service has its own contract test).
    text = re.sub(r'checkpoint = "[^"]*"', f'checkpoint = "{tmp}/no-policy.pt"', text)
    text = re.sub(r"port = 8080", f"port = {free_port()}", text)
    text = re.sub(r'directory = "[^"]*"', f'directory = "{tmp}/recordings"', text)
    deployment = tmp / "sim.toml"
    deployment.write_text(text)
    log = (tmp / "up.log").open("w")
    proc = subprocess.Popen([sys.executable, "-m", "shared.cli", "up", str(deployment), "--quiet"],
                            cwd=ROOT, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        deadline = time.time() + 90
        while time.time() < deadline:  # up when every registered key is being published
            reports = query(router, "xm/**/@health") if proc.poll() is None else []
            published = {k for r in reports for k, hz in r.get("published_hz", {}).items() if hz > 0}
            if {s.key for s in keys.REGISTRY} <= published:
                break
            time.sleep(2)
        else:
            pytest.fail(f"workcell did not come up; missing {sorted({s.key for s in keys.REGISTRY} - published)}; "
                        f"log: {(tmp / 'up.log').read_text()[-3000:]}")
        yield {"router": router, "deployment": deployment, "tmp": tmp, "proc": proc}
    finally:
        os.killpg(proc.pid, signal.SIGINT)
        try:
            proc.wait(20)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
        log.close()


def test_recording_decodes_with_stock_readers_at_nominal_rates(workcell):
    out = workcell["tmp"] / "ten_seconds.mcap"
    subprocess.run([sys.executable, "-m", "shared.cli", "record", "--deployment", str(workcell["deployment"]),
                    "--duration", "10", "-o", str(out)], cwd=ROOT, check=True, timeout=60)
    from mcap_ros2.reader import read_ros2_messages

    stamps: dict[str, list[float]] = defaultdict(list)
    for m in read_ros2_messages(str(out)):
        header = getattr(m.ros_msg, "header", None)
        t = (header.stamp.sec + header.stamp.nanosec * 1e-9) if header is not None else \
            (m.ros_msg.clock.sec + m.ros_msg.clock.nanosec * 1e-9)
        stamps[m.channel.topic].append(t)
    from rosbags.highlevel import AnyReader

    from shared.msgs import typestore

    rosbags_counts: dict[str, int] = defaultdict(int)
    with AnyReader([out], default_typestore=typestore()) as reader:
        for conn, _, raw in reader.messages():
            reader.deserialize(raw, conn.msgtype)
            rosbags_counts[conn.topic] += 1
    problems = []
    for spec in keys.REGISTRY:
        ts = sorted(stamps.get(spec.key, []))
        if rosbags_counts.get(spec.key, 0) != len(ts):
            problems.append(f"{spec.key}: rosbags read {rosbags_counts.get(spec.key, 0)}, mcap_ros2 {len(ts)}")
        if len(ts) < 3:
            problems.append(f"{spec.key}: only {len(ts)} messages")
            continue
        rate = (len(ts) - 1) / (ts[-1] - ts[0])  # in the deployment's time base (sim time)
        low, high = 0.8 * spec.rate_hz, (np.inf if spec.on_change else 1.2 * spec.rate_hz)
        if not low <= rate <= high:
            problems.append(f"{spec.key}: {rate:.1f} Hz, nominal {spec.rate_hz} Hz")
    assert not problems, "\n".join(problems)


def test_killed_service_is_restarted_and_publishes_again(workcell):
    router = workcell["router"]
    sup = next(r for r in query(router, "xm/deploy/supervisor/@health"))
    child = next(c for c in sup["children"] if c["service"] == "recon")
    os.kill(child["pid"], signal.SIGKILL)
    deadline = time.time() + 30
    while time.time() < deadline:
        time.sleep(1)
        sup = next(iter(query(router, "xm/deploy/supervisor/@health")), None)
        now = next((c for c in sup["children"] if c["service"] == "recon"), None) if sup else None
        if now and now["restarts"] >= 1 and now["pid"] and now["pid"] != child["pid"]:
            health = query(router, "xm/recon/main/@health")
            if health and health[0]["published_hz"].get("xm/recon/main/scene", 0) > 0:
                return
    pytest.fail(f"recon was not restarted and publishing within 30 s: {now}")


def test_status_lists_every_service(workcell):
    out = subprocess.run([sys.executable, "-m", "shared.cli", "status", str(workcell["deployment"])],
                         cwd=ROOT, capture_output=True, text=True, timeout=30)
    assert out.returncode == 0, out.stderr
    for svc in ("world", "glove/left", "glove/right", "camhub", "recon", "policy", "trajopt", "robot", "panel"):
        assert svc in out.stdout


RECOVERY_S = 3.0  # the target: every key on the new timeline within this long of the world restarting


class Timeline:
    """Per registered key, the header stamps (sim time) of what arrives, for seeing a world restart."""

    def __init__(self, router: str) -> None:
        from shared import msgs
        from shared.runtime import open_client

        self._msgs = msgs
        self.session = open_client(router)
        self.stamps: dict[str, list[float]] = defaultdict(list)
        self._sub = self.session.declare_subscriber("xm/**", self._on)

    def _on(self, sample) -> None:
        key = str(sample.key_expr)
        spec = keys.BY_KEY.get(key)
        if spec is None:
            return
        try:
            msg = self._msgs.deserialize(sample.payload.to_bytes(), spec.msgtype)
        except self._msgs.MessageError:
            return
        stamp = msg.clock if spec.msgtype == "rosgraph_msgs/msg/Clock" else msg.header.stamp
        self.stamps[key].append(self._msgs.stamp_seconds(stamp))

    def latest_clock(self) -> float:
        return self.stamps["xm/clock"][-1]

    def missing_since_restart(self, before: float) -> list[str]:
        """Registered keys with no message stamped on the new timeline (well before ``before``)."""
        return sorted(s.key for s in keys.REGISTRY if not any(t < before - 1.0 for t in self.stamps[s.key][-50:]))

    def close(self) -> None:
        self._sub.undeclare()
        self.session.close()


def _restart_and_check(workcell, restart) -> None:
    timeline = Timeline(workcell["router"])
    try:
        assert wait_until(lambda: timeline.stamps["xm/clock"] and timeline.latest_clock() > 5.0, 60)
        before = timeline.latest_clock()
        restart()
        # The world itself back (for a kill: a new process, imports and all; its start time is
        # bench/soak.py's figure), then every other key within the target.
        assert wait_until(lambda: timeline.stamps["xm/clock"][-1] < before - 1.0, 60), "the world did not restart"
        missing = wait_until(lambda: not timeline.missing_since_restart(before), RECOVERY_S)
        assert missing, f"silent on the new timeline {RECOVERY_S} s after the world restarted: " \
                        f"{timeline.missing_since_restart(before)}"
        reports = query(workcell["router"], "xm/**/@health")
        robot = next(r for r in reports if r["service"] == "robot")
        assert "no feedback" not in robot["message"], robot
        survivors = [r for r in reports if r["service"] not in ("world", "deploy") and r["uptime_s"] > 10]
        assert all(r["clock_jumps"] >= 1 and r["errors"].get("clock_jumped_back") for r in survivors), \
            [(r["service"], r["clock_jumps"]) for r in survivors]
    finally:
        timeline.close()


def wait_until(predicate, timeout: float) -> bool:
    deadline = time.time() + timeout
    while time.time() < deadline:
        if predicate():
            return True
        time.sleep(0.05)
    return bool(predicate())


def test_every_service_publishes_again_after_a_world_reset(workcell):
    _restart_and_check(workcell, lambda: query(workcell["router"], "xm/world/sim/@cmd/reset"))


def test_every_service_publishes_again_after_the_world_is_killed(workcell):
    sup = next(r for r in query(workcell["router"], "xm/deploy/supervisor/@health"))
    world = next(c for c in sup["children"] if c["service"] == "world")
    _restart_and_check(workcell, lambda: os.kill(world["pid"], signal.SIGKILL))
