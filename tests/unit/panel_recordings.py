"""Demonstration recordings for the panel's library and review tests, written by the recorder's own
writer (``McapRecorder``) with synthetic messages and log times."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from services.recorder.writer import McapRecorder
from shared import msgs

T0 = 1_700_000_000_000_000_000  # log time of the first message, ns
SCENE_HZ = 20.0
TACTILE_HZ = 100.0
IMAGE_HZ = 5.0


def _header(t: float, frame: str = "world"):
    return msgs.header(T0 * 1e-9 + t, frame)


def scene(t: float, masked: bool = False, x: float = 0.0) -> bytes:
    """Two hands whose keypoints sit at ``x`` (metres), half the left hand's unobserved when ``masked``."""
    rng = np.random.default_rng(int(t * 1000))
    kp = rng.uniform(-0.05, 0.05, (2, 21, 3)).astype(np.float32)
    kp[..., 0] += x
    kp[..., 2] += 0.1
    mask = np.ones(42, np.uint8)
    if masked:
        mask[:11] = 0
    return msgs.serialize(msgs.make(
        "xm_msgs/msg/Scene", header=_header(t), hand_names=["left", "right"], hand_keypoints=kp.ravel(),
        hand_mask=mask, object_names=["cup/rim"], object_keypoints=np.array([x, 0.1, 0.05], np.float32),
        object_mask=np.ones(1, np.uint8), tactile_regions=[], tactile=np.zeros(0, np.float32),
        tactile_mask=np.zeros(0, np.uint8)))


def tactile(t: float, hand: str, sequence: int, level: float = 10.0) -> bytes:
    return msgs.serialize(msgs.make(
        "xm_msgs/msg/Tactile", header=_header(t), hand=hand, rows=16, cols=16,
        pressure=np.full(256, level, np.float32), mask=np.ones(256, np.uint8), sequence=sequence))


def session(t: float, task: str = "pick_place", demo: int = 0) -> bytes:
    return msgs.serialize(msgs.make("xm_msgs/msg/Session", header=_header(t), task=task, demo=demo,
                                    phase="grasp", tactile_hand="right", seed_layout='{"cup": [0.1, 0.0]}'))


def image(t: float, cam: str, shade: int) -> bytes:
    img = np.full((48, 64, 3), shade, np.uint8)
    data = cv2.imencode(".jpg", img)[1].tobytes()
    return msgs.serialize(msgs.make("sensor_msgs/msg/CompressedImage", header=_header(t, cam), format="jpeg",
                                    data=np.frombuffer(data, np.uint8)))


def write_demo(path: Path, seconds: float = 2.0, task: str = "pick_place", masked: tuple[float, float] = (0.5, 1.0),
               lost: tuple[float, int] = (1.2, 7), cameras: tuple[str, ...] = ("cam0", "cam1"),
               keys: tuple[str, ...] = ("scene", "session", "tactile", "image"), close: bool = True,
               offset: float = 0.0) -> Path:
    """A recording of ``seconds``: scenes at 20 Hz (hands moving along x from 0 to 0.2 m, half the
    left hand unobserved within ``masked``), the right glove at 100 Hz losing ``lost[1]`` frames at
    ``lost[0]`` s, camera images at 5 Hz growing brighter, session labels at 1 Hz. ``close=False``
    leaves it as a killed recorder would (flushed, no footer); ``offset`` shifts every log time (s)."""
    rec = McapRecorder(path if close else path.with_name("whole-" + path.name), {"deployment": "test"})

    def put(key: str, msgtype: str, t: float, data: bytes) -> None:
        rec.write(key, msgtype, data, log_time_ns=T0 + int(round((t + offset) * 1e9)))

    events: list[tuple[float, str, str, bytes]] = []
    if "scene" in keys:
        for i in range(int(seconds * SCENE_HZ) + 1):
            t = i / SCENE_HZ
            events.append((t, "xm/recon/main/scene", "xm_msgs/msg/Scene",
                           scene(t, masked[0] <= t < masked[1], 0.2 * t / seconds)))
    if "session" in keys:
        for i in range(int(seconds) + 1):
            events.append((float(i), "xm/world/sim/session", "xm_msgs/msg/Session", session(i, task)))
    if "tactile" in keys:
        seq = 0
        for i in range(int(seconds * TACTILE_HZ) + 1):
            t = i / TACTILE_HZ
            seq += 1
            if abs(t - lost[0]) < 0.5 / TACTILE_HZ:
                seq += lost[1] - 1
                continue  # the frames the glove lost: its counter jumps past them
            events.append((t, "xm/glove/right/tactile", "xm_msgs/msg/Tactile",
                           tactile(t, "right", seq, 30 * t / seconds)))
    if "image" in keys:
        for i in range(int(seconds * IMAGE_HZ) + 1):
            t = i / IMAGE_HZ
            for cam in cameras:
                events.append((t, f"xm/camhub/{cam}/image", "sensor_msgs/msg/CompressedImage",
                               image(t, cam, int(40 + 200 * t / seconds))))
    for t, key, msgtype, data in sorted(events, key=lambda e: e[0]):
        put(key, msgtype, t, data)
    rec.flush()
    if not close:
        path.write_bytes(rec.path.read_bytes())  # the file as a kill -9 leaves it: no summary, no footer
    rec.close()
    if not close:
        rec.path.unlink()
    return path
