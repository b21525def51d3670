"""Camera rigs. ``SimRig`` asks the world to render a synchronized frame set over Zenoh (the
simulated hub); ``V4L2Rig`` grabs from video devices on the workcell (untested here: no cameras)."""

from __future__ import annotations

import json

import numpy as np

from shared.protocols import camera_frames
from shared.protocols.camera_frames import CameraFrame

RENDER_KEY = "xm/world/sim/@render"


class RigError(RuntimeError):
    """The rig delivered no frames (world not running, device missing)."""


class SimRig:
    def __init__(self, session, timeout_s: float = 1.0) -> None:
        self._session = session
        self._timeout = timeout_s

    def trigger(self) -> tuple[float, list[CameraFrame]]:
        """Blocking: call from a worker thread."""
        for reply in self._session.get(RENDER_KEY, payload=json.dumps({}), timeout=self._timeout):
            if reply.ok is not None:
                return camera_frames.unpack(reply.ok.payload.to_bytes())
            raise RigError(f"world refused to render: {reply.err.payload.to_bytes().decode(errors='replace')}")
        raise RigError(f"no answer from {RENDER_KEY} within {self._timeout}s (is the world running?)")


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
        import time

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
