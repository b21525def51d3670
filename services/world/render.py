"""Rendering of the camera rig on its own thread, from snapshots of the simulation state.

The physics loop never waits for OpenGL: a render request takes a snapshot of the state on the
loop (microseconds), and a worker thread with its own MjData and GL context renders all cameras
and answers the query. Software GL (OSMesa/EGL on llvmpipe) is slow, so one request at a time.
"""

from __future__ import annotations

import os
import queue
import threading
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

os.environ.setdefault("MUJOCO_GL", "egl")
import mujoco  # noqa: E402  (MUJOCO_GL must be set first)


@dataclass
class Snapshot:
    time: float
    qpos: np.ndarray
    mocap_pos: np.ndarray
    mocap_quat: np.ndarray


def snapshot(data: mujoco.MjData) -> Snapshot:
    return Snapshot(float(data.time), data.qpos.copy(), data.mocap_pos.copy(), data.mocap_quat.copy())


class RenderWorker:
    def __init__(self, model: mujoco.MjModel, cameras: list[str], width: int, height: int) -> None:
        self.model = model
        self.cameras = cameras
        self.width, self.height = width, height
        self._jobs: queue.Queue = queue.Queue(maxsize=1)
        self._thread = threading.Thread(target=self._work, name="render", daemon=True)
        self.error: str | None = None
        self.busy_drops = 0
        self._thread.start()

    def submit(self, snap: Snapshot, done: Callable[[float, list[np.ndarray] | None, str | None], None]) -> None:
        try:
            self._jobs.put_nowait((snap, done))
        except queue.Full:
            self.busy_drops += 1
            done(snap.time, None, "renderer busy with the previous trigger")

    def _work(self) -> None:
        try:
            renderer = mujoco.Renderer(self.model, self.height, self.width)
            data = mujoco.MjData(self.model)
        except Exception as exc:  # no GL: report on every request instead of dying
            self.error = (f"offscreen rendering unavailable ({exc}); install libegl1 or libosmesa6 "
                          f"and set MUJOCO_GL=egl or osmesa")
            renderer = None
        while True:
            job = self._jobs.get()
            if job is None:
                break
            snap, done = job
            if renderer is None:
                done(snap.time, None, self.error)
                continue
            data.qpos[:] = snap.qpos
            data.mocap_pos[:] = snap.mocap_pos
            data.mocap_quat[:] = snap.mocap_quat
            data.time = snap.time
            mujoco.mj_forward(self.model, data)
            images = []
            for cam in self.cameras:
                renderer.update_scene(data, cam)
                images.append(renderer.render().copy())
            done(snap.time, images, None)
        if renderer is not None:
            renderer.close()

    def close(self) -> None:
        try:
            self._jobs.put_nowait(None)
        except queue.Full:
            pass
        self._thread.join(timeout=2.0)
