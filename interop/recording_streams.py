"""The streams of one recording an export needs: scenes, session labels, robot joint states and
camera frames, each with its header stamps, and the demonstrations cut from them."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from learning.dataset import SCENE_KEY, SESSION_KEY, DatasetError, demos_from_messages
from services.recorder.writer import read_messages
from shared import msgs
from shared.demo import Demo
from shared.recording_files import recording_segments

ROBOT_STATE = "sensor_msgs/msg/JointState"
IMAGE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"


@dataclass
class Stream:
    """Samples of one key in stamp order: stamps (s) and one value per stamp."""

    stamps: list[float] = field(default_factory=list)
    values: list = field(default_factory=list)

    def add(self, stamp: float, value: object) -> None:
        self.stamps.append(stamp)
        self.values.append(value)

    def sorted(self) -> Stream:
        order = np.argsort(np.asarray(self.stamps), kind="stable")
        return Stream([self.stamps[i] for i in order], [self.values[i] for i in order])

    def at(self, times: np.ndarray) -> tuple[np.ndarray, float]:
        """Index of the latest sample at or before each time and the largest age (inf: none before
        the first time)."""
        st = np.asarray(self.stamps)
        idx = np.searchsorted(st, times, side="right") - 1
        if len(st) == 0 or (idx < 0).any():
            return np.full(len(times), -1), np.inf
        age = float((times - st[idx]).max())
        return idx, age


@dataclass
class Recording:
    """What one recording holds for an export."""

    source: str
    scenes: list = field(default_factory=list)  # (stamp, Scene)
    sessions: list = field(default_factory=list)  # (stamp, Session)
    robots: dict[str, Stream] = field(default_factory=dict)  # state key -> JointState
    images: dict[str, Stream] = field(default_factory=dict)  # camera -> JPEG bytes
    infos: dict[str, dict[float, tuple]] = field(default_factory=dict)  # camera -> stamp -> (h, w, roi)
    malformed: int = 0


def camera_of(key: str) -> str:
    return key.split("/")[2]


def read_recording(path: str | Path) -> Recording:
    """One pass over a recording (any of the forms of docs/recording.md); undecodable messages are
    counted in ``malformed`` and left out."""
    files = recording_segments(path)
    if not files or not all(f.exists() for f in files):
        raise DatasetError(f"{path}: no such recording")
    rec = Recording(source=str(path))
    for s in read_messages(files):
        kind = _kind(s.key, s.msgtype)
        if kind is None:
            continue
        try:
            msg = msgs.deserialize(s.data, s.msgtype)
        except msgs.MessageError:
            rec.malformed += 1
            continue
        t = msgs.stamp_seconds(msg.header.stamp)
        if kind == "scene":
            rec.scenes.append((t, msg))
        elif kind == "session":
            rec.sessions.append((t, msg))
        elif kind == "robot":
            rec.robots.setdefault(s.key, Stream()).add(t, (list(msg.name), np.array(msg.position, np.float32)))
        elif kind == "image":
            rec.images.setdefault(camera_of(s.key), Stream()).add(t, bytes(msg.data))
        else:
            roi = (msg.roi.x_offset, msg.roi.y_offset, msg.roi.width, msg.roi.height)
            rec.infos.setdefault(camera_of(s.key), {})[t] = (int(msg.height), int(msg.width), roi)
    rec.robots = {k: v.sorted() for k, v in rec.robots.items()}
    rec.images = {k: v.sorted() for k, v in rec.images.items()}
    return rec


def _kind(key: str, msgtype: str) -> str | None:
    if key == SCENE_KEY:
        return "scene"
    if key == SESSION_KEY:
        return "session"
    parts = key.split("/")
    if msgtype == ROBOT_STATE and parts[1] == "robot":
        return "robot"
    if parts[1] == "camhub" and msgtype in (IMAGE, CAMERA_INFO):
        return "image" if msgtype == IMAGE else "info"
    return None


def demos_with_starts(rec: Recording, dt: float, report: list[str]) -> list[tuple[Demo, float]]:
    """The recording's demonstrations (``learning.dataset`` rules) with the stamp of each one's first step."""
    if not rec.scenes or not rec.sessions:
        missing = [k for k, v in ((SCENE_KEY, rec.scenes), (SESSION_KEY, rec.sessions)) if not v]
        raise DatasetError(f"{rec.source}: no messages on {', '.join(missing)}")
    demos = demos_from_messages(rec.scenes, rec.sessions, dt, report=report, source=rec.source)
    return [(d, d.meta["start_s"]) for d in demos]


def camera_frame(jpeg: bytes, size: tuple[int, int], info: tuple | None) -> np.ndarray:
    """An RGB frame of ``size`` (h, w): a region-of-interest window pasted where the camera info says
    it lies in the full frame (black around it), a full frame of another size resized."""
    img = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
    if img is None:
        raise ValueError("undecodable JPEG")
    img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    h, w = size
    if info is not None:
        x, y, rw, rh = info[2]
        if rw and rh and (rw, rh) != (w, h) and img.shape[:2] == (rh, rw) and x + rw <= w and y + rh <= h:
            out = np.zeros((h, w, 3), np.uint8)
            out[y:y + rh, x:x + rw] = img
            return out
    if img.shape[:2] != (h, w):
        img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
    return img


def camera_size(rec: Recording, camera: str) -> tuple[int, int] | None:
    """(h, w) of a camera's full frame: from its camera info, else its first decodable image."""
    infos = rec.infos.get(camera)
    if infos:
        h, w, _ = next(iter(infos.values()))
        if h and w:
            return h, w
    for jpeg in rec.images[camera].values[:5]:
        img = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
        if img is not None:
            return img.shape[0], img.shape[1]
    return None
