"""Rendering the simulated camera rig from a snapshot of the world's state.

The world answers ``xm/world/sim/@snapshot`` with its joint positions and mocap poses (a few
hundred bytes); the simulated camera hub renders all cameras from that snapshot in its own
process, so the physics loop never waits for software OpenGL. A renderer belongs to the thread
that created it (GL contexts are per thread).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass

import numpy as np

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("LP_NUM_THREADS", "1")  # llvmpipe: one thread; its extra threads only fight the services
import mujoco  # noqa: E402  (MUJOCO_GL must be set first)

from services.world.model import build_model, camera_specs  # noqa: E402
from shared.robots.registry import DEFAULT_ROBOT  # noqa: E402


@dataclass
class Snapshot:
    task: str
    time: float
    qpos: np.ndarray
    mocap_pos: np.ndarray
    mocap_quat: np.ndarray
    robot: str = DEFAULT_ROBOT

    def to_json(self) -> str:
        return json.dumps({"task": self.task, "robot": self.robot, "time": self.time, "qpos": self.qpos.tolist(),
                           "mocap_pos": self.mocap_pos.tolist(), "mocap_quat": self.mocap_quat.tolist()})

    @classmethod
    def from_json(cls, text: str | bytes) -> Snapshot:
        d = json.loads(text)
        return cls(d["task"], float(d["time"]), np.array(d["qpos"]), np.array(d["mocap_pos"]),
                   np.array(d["mocap_quat"]), d.get("robot", DEFAULT_ROBOT))


def snapshot(task: str, data: mujoco.MjData, robot: str = DEFAULT_ROBOT) -> Snapshot:
    return Snapshot(task, float(data.time), data.qpos.copy(), data.mocap_pos.copy(), data.mocap_quat.copy(), robot)


class SceneRenderer:
    """All cameras of the rig for one task and robot; create and use it on one thread."""

    def __init__(self, task: str, width: int = 320, height: int = 240, robot: str = DEFAULT_ROBOT) -> None:
        self.task = task
        self.robot = robot
        self.model = build_model(task, width, height, robot)
        self.data = mujoco.MjData(self.model)
        self.cameras = camera_specs(width, height)
        try:
            self.renderer = mujoco.Renderer(self.model, height, width)
        except Exception as exc:
            raise RuntimeError(f"offscreen rendering unavailable ({exc}); install libegl1 (or libosmesa6 and "
                               f"set MUJOCO_GL=osmesa)") from exc

    def render(self, snap: Snapshot) -> list[np.ndarray]:
        d = self.data
        d.qpos[:] = snap.qpos
        d.mocap_pos[:] = snap.mocap_pos
        d.mocap_quat[:] = snap.mocap_quat
        d.time = snap.time
        mujoco.mj_forward(self.model, d)
        images = []
        for cam in self.cameras:
            self.renderer.update_scene(d, cam.name)
            images.append(self.renderer.render().copy())
        return images

    def close(self) -> None:
        self.renderer.close()
