"""Demonstration sessions for the LeRobot export tests, written by the recorder's own writer
(``McapRecorder``): scenes with hands, objects and tactile regions, session labels, the robot's
joint states and camera frames with their camera info (windows around the hands on some frames)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from services.recorder.writer import McapRecorder
from shared import msgs

T0 = 1_700_000_000_000_000_000  # log time of the first message, ns
SCENE_HZ = 20.0
ROBOT_HZ = 100.0
IMAGE_HZ = 5.0
JOINTS = ["x", "y", "z", "yaw"]
OBJECTS = ["lens/center", "lens/edge", "housing/center"]
FULL = (48, 64)  # camera full frame (h, w)


def _scene(t: float, start: float, demo: int, rng: np.random.Generator) -> bytes:
    kp = (rng.normal(0.0, 0.05, (2, 21, 3)) + [0.1 * (t - start), 0.0, 0.1]).astype(np.float32)
    mask = np.ones(42, np.uint8)
    if int(round((t - start) * SCENE_HZ)) % 7 == 0:
        mask[3:9] = 0  # some fingers unobserved now and then
    obj = (rng.normal(0.0, 0.02, (3, 3)) + [0.3, 0.05 * demo, 0.02]).astype(np.float32)
    tact = np.abs(rng.normal(5.0, 2.0, 12)).astype(np.float32)
    tmask = np.r_[np.zeros(6), np.ones(6)].astype(np.uint8)
    return msgs.serialize(msgs.make(
        "xm_msgs/msg/Scene", header=msgs.header(t), hand_names=["left", "right"], hand_keypoints=kp.ravel(),
        hand_mask=mask, object_names=OBJECTS, object_keypoints=obj.ravel(), object_mask=np.ones(3, np.uint8),
        tactile_regions=["thumb", "index", "middle", "ring", "little", "palm"], tactile=tact, tactile_mask=tmask))


def _session(t: float, demo: int, phase: str) -> bytes:
    return msgs.serialize(msgs.make("xm_msgs/msg/Session", header=msgs.header(t), task="assembly", demo=demo,
                                    phase=phase, tactile_hand="right", seed_layout="{}"))


def _joints(t: float, names: list[str]) -> bytes:
    q = np.array([0.1 * np.sin(t + i) for i in range(len(names))], float)
    return msgs.serialize(msgs.make("sensor_msgs/msg/JointState", header=msgs.header(t), name=names, position=q,
                                    velocity=np.zeros(len(names)), effort=np.zeros(len(names))))


def _image(t: float, cam: str, roi: bool) -> tuple[bytes, bytes]:
    h, w = (24, 32) if roi else FULL
    img = np.full((h, w, 3), int(40 + 20 * t) % 256, np.uint8)
    data = cv2.imencode(".jpg", img)[1]
    image = msgs.serialize(msgs.make("sensor_msgs/msg/CompressedImage", header=msgs.header(t, cam), format="jpeg",
                                     data=np.asarray(data, np.uint8).ravel()))
    info = msgs.serialize(msgs.make(
        "sensor_msgs/msg/CameraInfo", header=msgs.header(t, cam), height=FULL[0], width=FULL[1],
        distortion_model="plumb_bob", d=np.zeros(5), k=np.eye(3).ravel(), r=np.eye(3).ravel(),
        p=np.zeros(12), binning_x=0, binning_y=0,
        roi=msgs.make("sensor_msgs/msg/RegionOfInterest", x_offset=8 if roi else 0, y_offset=4 if roi else 0,
                      height=h if roi else 0, width=w if roi else 0, do_rectify=False)))
    return image, info


def write_session(path: Path, demos: int = 3, seconds: float = 1.5, pause: float = 0.5, seed: int = 0,
                  robot: bool = True, cameras: tuple[str, ...] = ("cam0", "cam1"),
                  robot_stops: float | None = None, joint_names: list[str] | None = None) -> Path:
    """``demos`` demonstrations of ``seconds`` each, ``pause`` apart (no scenes in between). The robot's
    state stops at ``robot_stops`` seconds after the start when given."""
    rng = np.random.default_rng(seed)
    rec = McapRecorder(path, {"deployment": "test"})
    events: list[tuple[float, str, str, bytes]] = []
    names = joint_names or JOINTS
    span = 1.0 + demos * (seconds + pause)
    for d in range(demos):
        start = 1.0 + d * (seconds + pause)  # the first label at 1 s: stamps stay positive
        for i in range(int(seconds * SCENE_HZ) + 1):
            t = start + i / SCENE_HZ
            events.append((t, "xm/recon/main/scene", "xm_msgs/msg/Scene", _scene(t, start, d, rng)))
        for i, phase in enumerate(("approach", "grasp", "place")):
            t = start + i * seconds / 3
            events.append((t - 1e-3, "xm/world/sim/session", "xm_msgs/msg/Session", _session(t - 1e-3, d, phase)))
    if robot:
        end = span if robot_stops is None else robot_stops
        for i in range(int(end * ROBOT_HZ)):
            t = i / ROBOT_HZ
            events.append((t, "xm/robot/workcell/state", "sensor_msgs/msg/JointState", _joints(t, names)))
    for i in range(int(span * IMAGE_HZ) + 1):
        t = i / IMAGE_HZ
        for cam in cameras:
            image, info = _image(t, cam, roi=i % 2 == 1)
            events.append((t, f"xm/camhub/{cam}/image", "sensor_msgs/msg/CompressedImage", image))
            events.append((t, f"xm/camhub/{cam}/info", "sensor_msgs/msg/CameraInfo", info))
    for t, key, msgtype, data in sorted(events, key=lambda e: e[0]):
        rec.write(key, msgtype, data, log_time_ns=T0 + int(round((t + 1.0) * 1e9)))
    rec.close()
    return path
