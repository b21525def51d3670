"""Contract of the panel service: one process, seen only through Zenoh and its TCP port."""

from __future__ import annotations

import contextlib
import socket
import subprocess
import sys
import threading
import time
import urllib.request

import msgspec
import numpy as np
import viser
from websockets.sync.client import connect

from services.glove.layout import pressure_from_forces
from services.recon.tactile_projection import TactileProjector
from shared import msgs
from shared.geometry import look_at, projection
from shared.kinematics import load_robot
from tests.conftest import ROOT, ServiceProcess, free_port, query_json, wait_for, write_deployment
from tests.unit.test_tactile_projection import hand


@contextlib.contextmanager
def viser_client(port: int):
    """A bare websocket client speaking viser's subprotocol; viser counts a client once it reports its camera."""
    ws = connect(f"ws://127.0.0.1:{port}", subprotocols=[f"viser-v{viser.__version__}"], max_size=None)
    ws.send(msgspec.msgpack.encode({
        "type": "ViewerCameraMessage", "wxyz": [1.0, 0.0, 0.0, 0.0], "position": [1.0, -1.0, 1.0], "fov": 1.0,
        "near": 0.01, "far": 100.0, "image_height": 480, "image_width": 640, "look_at": [0.0, 0.0, 0.0],
        "up_direction": [0.0, 0.0, 1.0]}))

    def drain() -> None:  # read (and drop) what the server sends so its buffers never fill
        with contextlib.suppress(Exception):
            while True:
                ws.recv()

    reader = threading.Thread(target=drain, daemon=True)
    reader.start()
    try:
        yield ws
    finally:
        ws.close()
        reader.join(5)


def health_of(session) -> dict | None:
    rep = query_json(session, "xm/panel/main/@health")
    return rep[0] if rep else None


def joint_state() -> object:
    names = load_robot("workcell").joint_names
    return msgs.make("sensor_msgs/msg/JointState", header=msgs.header(time.time()), name=names,
                     position=np.full(len(names), 0.05), velocity=np.zeros(len(names)),
                     effort=np.zeros(len(names)))


def scene() -> object:
    rng = np.random.default_rng(1)
    return msgs.make(
        "xm_msgs/msg/Scene", header=msgs.header(time.time()), hand_names=["left", "right"],
        hand_keypoints=rng.uniform(-0.2, 0.2, 2 * 21 * 3).astype(np.float32),
        hand_mask=np.ones(42, np.uint8), object_names=["cup/rim", "cup/base"],
        object_keypoints=np.array([0.1, 0.0, 0.05, 0.1, 0.0, 0.0], np.float32), object_mask=np.ones(2, np.uint8),
        tactile_regions=["thumb"], tactile=np.zeros(2, np.float32), tactile_mask=np.zeros(2, np.uint8))


def tactile(hand: str) -> object:
    return msgs.make("xm_msgs/msg/Tactile", header=msgs.header(time.time()), hand=hand, rows=16, cols=16,
                     pressure=np.linspace(0, 30, 256, dtype=np.float32), mask=np.ones(256, np.uint8), sequence=1)


def tactile_mesh() -> object:
    """recon's TactileMesh of a right hand above the table, fingers up, palm toward -y, pinching:
    thumb and index pressed (27 kPa), the palm lightly (2.7 kPa)."""
    kp = hand("right", curl=0.5, rot=(1.209, 1.209, 1.209), at=(0.0, 0.0, 0.15))
    pressure = pressure_from_forces(np.array([8.0, 8.0, 0.0, 0.0, 0.0, 2.0]))
    msg, _ = TactileProjector().message(time.time(), ["right"], kp[None], np.ones((1, 21)), {"right": pressure})
    return msg


def plan() -> object:
    steps, names = 5, ["left/8", "right/8"]
    pos = np.linspace(0.0, 0.2, steps * len(names) * 3, dtype=np.float32)
    return msgs.make("xm_msgs/msg/Plan", header=msgs.header(time.time()), policy="test", dt=0.1, steps=steps,
                     point_names=names, positions=pos, mask=np.ones(steps * len(names), np.uint8),
                     efforts=np.zeros(0, np.float32))


def trajectory(knots: int = 5) -> object:
    """trajopt's JointTrajectory: ``knots`` knots of the workcell moving its left carriage."""
    names = list(load_robot("workcell").joint_names)
    q = np.zeros((knots, len(names)))
    q[:, 0] = np.linspace(0.0, 0.1, knots)
    points = [msgs.make("trajectory_msgs/msg/JointTrajectoryPoint", positions=qk, velocities=np.zeros(0),
                        accelerations=np.zeros(0), effort=np.zeros(0),
                        time_from_start=msgs.make("builtin_interfaces/msg/Duration", sec=0, nanosec=k * 50_000_000))
              for k, qk in enumerate(q)]
    return msgs.make("trajectory_msgs/msg/JointTrajectory", header=msgs.header(time.time(), "world"),
                     joint_names=names, points=points)


def camera_info() -> object:
    K = np.array([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]])
    P = projection(K, look_at(np.array([0.4, -0.4, 0.8]), np.zeros(3)))
    return msgs.make("sensor_msgs/msg/CameraInfo", header=msgs.header(time.time(), "cam0"), height=240, width=320,
                     distortion_model="plumb_bob", d=np.zeros(5), k=K.ravel(), r=np.eye(3).ravel(), p=P.ravel(),
                     binning_x=0, binning_y=0,
                     roi=msgs.make("sensor_msgs/msg/RegionOfInterest", x_offset=0, y_offset=0, height=0, width=0,
                                   do_rectify=False))


def test_panel_serves_http_and_reports_what_it_received(router, tmp_path):
    endpoint, session = router
    port = free_port()
    dep = write_deployment(tmp_path / "d.toml", endpoint, {"panel": {"main": {"port": port}}})
    panel = ServiceProcess("panel", dep, "main", tmp_path / "panel.log")
    try:
        health = wait_for(lambda: query_json(session, "xm/panel/main/@health"), 30)
        assert health, panel.output()
        h = health[0]
        assert h["status"] == "ok" and h["url"] == f"http://127.0.0.1:{port}"
        assert h["clients"] == 0 and h["robot_model"] is True
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=10) as resp:  # the viser client
            assert resp.status == 200 and b"<html" in resp.read().lower()

        frames = {"xm/robot/workcell/state": joint_state(), "xm/recon/main/scene": scene(),
                  "xm/glove/left/tactile": tactile("left"), "xm/glove/right/tactile": tactile("right"),
                  "xm/camhub/cam0/info": camera_info(), "xm/policy/main/plan": plan(),
                  "xm/recon/main/tactile_mesh": tactile_mesh(), "xm/trajopt/main/trajectory": trajectory()}
        pubs = {k: session.declare_publisher(k) for k in frames}

        def received() -> dict | None:
            for k, pub in pubs.items():  # stamped now: the panel refuses stale stamps
                frames[k].header.stamp = msgs.stamp(time.time())
                pub.put(msgs.serialize(frames[k]))
            rep = query_json(session, "xm/panel/main/@health")
            return rep[0] if rep and set(frames) <= set(rep[0]["received_hz"]) else None

        h = wait_for(received, 20)
        assert h, f"panel did not receive every key: {query_json(session, 'xm/panel/main/@health')}"
        assert not h["errors"], h["errors"]

        with viser_client(port):  # with a viewer connected the render loop draws every message kind
            h = wait_for(lambda: (r := received()) and r["clients"] == 1 and r["frames_drawn"] > 3 and r, 20)
            assert h, health_of(session)
            assert h["frustums"] == ["cam0"] and "draw_error" not in h["errors"], (h["errors"], panel.output())
            assert h["tactile_meshes"] == ["right"], "the gloved hand's tactile mesh is drawn"
            assert h["trajectory"]["drawn"] > 0 and h["trajectory"]["shown"], h["trajectory"]
            assert h["trajectory"]["frames"] == ["left_tip_a", "left_tip_b", "right_tip"]
            frames["xm/trajopt/main/trajectory"] = trajectory(knots=0)  # a trajectory without points
            h = wait_for(lambda: (r := received()) and r["errors"].get("bad_trajectory") and r, 20)
            assert h and "draw_error" not in h["errors"], health_of(session)  # counted; the rest still draws

        pubs["xm/glove/left/tactile"].put(b"\x00\x01garbage")  # malformed: counted, not fatal
        h = wait_for(lambda: (r := query_json(session, "xm/panel/main/@health")) and
                     r[0]["errors"].get("malformed:xm/glove/left/tactile") and r[0], 10)
        assert h and h["status"] == "ok"
    finally:
        assert panel.stop() in (0, -15), panel.output()


def test_taken_port_exits_2_with_a_message_naming_it(router, tmp_path):
    endpoint, _session = router
    with socket.socket() as blocker:
        blocker.bind(("127.0.0.1", 0))
        blocker.listen(1)
        port = blocker.getsockname()[1]
        dep = write_deployment(tmp_path / "d.toml", endpoint, {"panel": {"main": {"port": port}}})
        proc = subprocess.run([sys.executable, "-m", "services.panel", "--deployment", str(dep), "--instance", "main"],
                              cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2, proc.stderr
    assert f"127.0.0.1:{port}" in proc.stderr and "port = " in proc.stderr
    assert "Traceback" not in proc.stderr


def test_without_a_robot_model_the_panel_draws_joint_markers(router, tmp_path):
    endpoint, session = router
    port = free_port()
    dep = write_deployment(tmp_path / "d.toml", endpoint, {"panel": {"main": {"port": port, "robot": "no_such"}}})
    panel = ServiceProcess("panel", dep, "main", tmp_path / "panel.log")
    try:
        h = wait_for(lambda: health_of(session), 30)
        assert h and h["status"] == "ok" and h["robot_model"] is False, panel.output()
        # the state of the robot the deployment names (xm/robot/<robot>/state), model file or not
        pub, payload = session.declare_publisher("xm/robot/no_such/state"), msgs.serialize(joint_state())

        def drawn() -> dict | None:
            pub.put(payload)
            r = health_of(session)
            return r if r and r["frames_drawn"] > 3 and "xm/robot/no_such/state" in r["received_hz"] else None

        with viser_client(port):
            h = wait_for(drawn, 20)
        assert h and "draw_error" not in h["errors"], (h, panel.output())
        assert "no robot model" in panel.output()
    finally:
        assert panel.stop() in (0, -15), panel.output()
