"""Camera rigs. ``SimRig``: the simulated hub; it fetches a state snapshot from the world and
renders every camera from it (MuJoCo, software OpenGL). ``V4L2Rig``: video devices on the
workcell (written for the hardware, untested here: no cameras on this machine)."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

SNAPSHOT_KEY = "xm/world/sim/@snapshot"


@dataclass
class CameraFrame:
    name: str
    K: np.ndarray  # (3,3) OpenCV intrinsics
    world_T_cam: np.ndarray  # (4,4) camera pose, OpenCV axes (x right, y down, z forward)
    image: np.ndarray  # (H,W,3) uint8 RGB


class RigError(RuntimeError):
    """The rig delivered no frames (world not running, device missing)."""


class SimRig:
    """Call ``trigger`` from one and the same worker thread (the GL context lives there)."""

    def __init__(self, session, width: int = 320, height: int = 240, timeout_s: float = 1.0) -> None:
        self._session = session
        self._timeout = timeout_s
        self._size = (width, height)
        self._renderer = None

    def trigger(self) -> tuple[float, list[CameraFrame]]:
        from services.world.render import SceneRenderer, Snapshot

        replies = [r for r in self._session.get(SNAPSHOT_KEY, timeout=self._timeout)]
        ok = [r.ok for r in replies if r.ok is not None]
        if not ok:
            raise RigError(f"no answer from {SNAPSHOT_KEY} within {self._timeout}s (is the world running?)")
        snap = Snapshot.from_json(ok[0].payload.to_bytes())
        if self._renderer is None or (self._renderer.task, self._renderer.robot) != (snap.task, snap.robot):
            if self._renderer is not None:
                self._renderer.close()
            self._renderer = SceneRenderer(snap.task, *self._size, robot=snap.robot)
        images = self._renderer.render(snap)
        return snap.time, [CameraFrame(c.name, c.K, c.world_T_cam, img)
                           for c, img in zip(self._renderer.cameras, images, strict=True)]

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()


class V4L2Rig:
    """Workcell cameras through OpenCV; intrinsics and poses from a calibration JSON."""

    def __init__(self, devices: list[str], calibration: dict) -> None:
        import cv2

        self._caps = [cv2.VideoCapture(d) for d in devices]
        self._calib = calibration
        missing = [d for d, c in zip(devices, self._caps, strict=True) if not c.isOpened()]
        if missing:
            raise RigError(f"cannot open camera device(s) {missing}")

    def trigger(self) -> tuple[float, list[CameraFrame]]:
        import cv2

        for cap in self._caps:  # grab all first: the frames are as close in time as the USB allows
            cap.grab()
        stamp = time.time()
        frames = []
        for i, cap in enumerate(self._caps):
            ok, bgr = cap.retrieve()
            if not ok:
                raise RigError(f"camera {i} returned no frame")
            cal = self._calib["cameras"][i]
            frames.append(CameraFrame(cal["name"], np.array(cal["K"]), np.array(cal["world_T_cam"]),
                                      cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)))
        return stamp, frames

    def close(self) -> None:
        for cap in self._caps:
            cap.release()
