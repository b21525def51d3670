"""Rendering the simulated camera rig from a snapshot of the world's state.

The world answers ``xm/world/sim/@snapshot`` with its joint positions, mocap poses and session (a
few hundred bytes); the simulated camera hub renders all cameras from that snapshot in its own
process, so the physics loop never waits for software OpenGL. A renderer belongs to the thread
that created it (GL contexts are per thread).

Each camera renders exactly its OpenCV intrinsics ``K`` (pixel centres at integer coordinates)
through an explicit OpenGL frustum, and a region of interest renders only that window of the
image at full resolution: the cost follows the pixels read out, as on the MT9P001 sensor whose
readout window the hub sets per frame (thesis 5.4).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass

import numpy as np

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("LP_NUM_THREADS", "1")  # llvmpipe: one thread; its extra threads only fight the services
import mujoco  # noqa: E402  (MUJOCO_GL must be set first)

from services.world.appearance import ROOM, Lighting, session_lighting, session_look, teacher_capsules  # noqa: E402
from services.world.model import CameraSpec, build_model, camera_specs  # noqa: E402
from shared.demo import HAND_NAMES  # noqa: E402

MAX_GEOM = 2000
Window = tuple[int, int, int, int]  # x_offset, y_offset, width, height in full-image pixels
from shared.robots.registry import DEFAULT_ROBOT  # noqa: E402


@dataclass
class Snapshot:
    task: str
    time: float
    qpos: np.ndarray
    mocap_pos: np.ndarray
    mocap_quat: np.ndarray
    robot: str = DEFAULT_ROBOT
    seed: int = 0  # the session's seed and demonstration: they pick the lighting and the teacher's look
    demo: int = 0
    glove_hand: str = ""  # the hand wearing the tactile glove ("" = none)

    def to_json(self) -> str:
        return json.dumps({"task": self.task, "robot": self.robot, "time": self.time, "qpos": self.qpos.tolist(),
                           "mocap_pos": self.mocap_pos.tolist(), "mocap_quat": self.mocap_quat.tolist(),
                           "seed": self.seed, "demo": self.demo, "glove_hand": self.glove_hand})

    @classmethod
    def from_json(cls, text: str | bytes) -> Snapshot:
        d = json.loads(text)
        return cls(d["task"], float(d["time"]), np.array(d["qpos"]), np.array(d["mocap_pos"]),
                   np.array(d["mocap_quat"]), d.get("robot", DEFAULT_ROBOT), int(d.get("seed", 0)),
                   int(d.get("demo", 0)), str(d.get("glove_hand", "")))


def snapshot(task: str, data: mujoco.MjData, robot: str = DEFAULT_ROBOT, seed: int = 0, demo: int = 0,
             glove_hand: str = "") -> Snapshot:
    return Snapshot(task, float(data.time), data.qpos.copy(), data.mocap_pos.copy(), data.mocap_quat.copy(), robot,
                    seed, demo, glove_hand)


def gl_frustum(K: np.ndarray, window: Window, near: float) -> tuple[float, float, float, float]:
    """``(center, half_width, bottom, top)`` of the OpenGL frustum at ``near`` that renders the pixel
    window ``(x0, y0, w, h)`` of a camera with OpenCV intrinsics K (no skew).

    OpenCV puts pixel centres at integers, so pixel column u spans [u - 0.5, u + 0.5]; the window's
    left edge is x0 - 0.5. OpenGL's y points up: image row 0 is the frustum's top."""
    x0, y0, w, h = window
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    left = near * (x0 - 0.5 - cx) / fx
    right = near * (x0 + w - 0.5 - cx) / fx
    top = near * (cy - (y0 - 0.5)) / fy
    bottom = near * (cy - (y0 + h - 0.5)) / fy
    return (left + right) / 2, (right - left) / 2, bottom, top


def _gl_context(width: int, height: int):
    """An offscreen GL context of the backend MUJOCO_GL names (egl by default). Chosen here, not at
    ``import mujoco``, because another module may have imported MuJoCo before MUJOCO_GL was set."""
    backend = os.environ.get("MUJOCO_GL", "egl").lower()
    if backend == "osmesa":
        from mujoco.osmesa import GLContext  # optional backend: imported only when asked for
    elif backend == "egl":
        from mujoco.egl import GLContext  # imports PyOpenGL's EGL platform
    else:
        GLContext = mujoco.GLContext
    return GLContext(width, height)


class SceneRenderer:
    """All cameras of the rig for one task and robot; create and use it on one thread."""

    def __init__(self, task: str, width: int = 320, height: int = 240, robot: str = DEFAULT_ROBOT) -> None:
        self.task = task
        self.robot = robot
        self.width, self.height = width, height
        self.model = build_model(task, width, height, robot)
        self.data = mujoco.MjData(self.model)
        self.cameras: list[CameraSpec] = camera_specs(width, height)
        self._cam_ids = [mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_CAMERA, c.name) for c in self.cameras]
        self._hand_mocap = np.array([[self.model.body_mocapid[self.model.body(f"{h}_kp{k}").id] for k in range(21)]
                                     for h in HAND_NAMES])
        self._session: tuple[int, int] | None = None
        self._look = session_look(0, 0)
        # Coarse tessellation: llvmpipe's cost is the hands' ~50 capsules per view, and 8 slices
        # still draw them round at 640x480.
        self.model.vis.quality.numslices, self.model.vis.quality.numstacks = 8, 4
        try:
            self._gl = _gl_context(max(width, 640), max(height, 480))
            self._gl.make_current()
            self._ctx = mujoco.MjrContext(self.model, mujoco.mjtFontScale.mjFONTSCALE_100)
        except Exception as exc:
            raise RuntimeError(f"offscreen rendering unavailable ({exc}); install libegl1 (or libosmesa6 and "
                               f"set MUJOCO_GL=osmesa)") from exc
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, self._ctx)
        self._scene = mujoco.MjvScene(self.model, maxgeom=MAX_GEOM)
        self._option = mujoco.MjvOption()
        self._near = float(self.model.vis.map.znear * self.model.stat.extent)
        self.model.light_type[:] = mujoco.mjtLightType.mjLIGHT_DIRECTIONAL

    def _set_session(self, seed: int, demo: int) -> None:
        if self._session == (seed, demo):
            return
        self._session = (seed, demo)
        self._look = session_look(seed, demo)
        light: Lighting = session_lighting(seed, demo)
        m = self.model
        m.light_pos[0], m.light_dir[0] = light.pos, light.dir
        m.light_diffuse[0], m.light_ambient[0] = light.diffuse, light.ambient
        m.vis.headlight.diffuse[:] = light.headlight
        m.vis.headlight.ambient[:] = 0.0

    def _add_decor(self, capsules: list) -> None:
        """The room and the teacher's hands, drawn into the scene (not part of the physics model)."""
        scn = self._scene
        for box in ROOM:
            if scn.ngeom < scn.maxgeom:
                mujoco.mjv_initGeom(scn.geoms[scn.ngeom], mujoco.mjtGeom.mjGEOM_BOX, box.half, box.pos,
                                    np.eye(3).ravel(), np.asarray(box.rgba, np.float32))
                scn.ngeom += 1
        for cap in capsules:
            if scn.ngeom >= scn.maxgeom:
                return
            g = scn.geoms[scn.ngeom]
            sphere = np.allclose(cap.a, cap.b)
            mujoco.mjv_initGeom(g, mujoco.mjtGeom.mjGEOM_SPHERE if sphere else mujoco.mjtGeom.mjGEOM_CAPSULE,
                                np.full(3, cap.radius), cap.a, np.eye(3).ravel(), np.asarray(cap.rgba, np.float32))
            if not sphere:
                mujoco.mjv_connector(g, mujoco.mjtGeom.mjGEOM_CAPSULE, cap.radius, cap.a, cap.b)
            scn.ngeom += 1

    def render(self, snap: Snapshot, windows: list[Window | None] | None = None) -> list[np.ndarray]:
        """One RGB image per camera: the full frame, or only ``windows[i]`` of camera i."""
        d = self.data
        d.qpos[:] = snap.qpos
        d.mocap_pos[:] = snap.mocap_pos
        d.mocap_quat[:] = snap.mocap_quat
        d.time = snap.time
        self._set_session(snap.seed, snap.demo)
        mujoco.mj_forward(self.model, d)
        hands = d.mocap_pos[self._hand_mocap]
        capsules = teacher_capsules(hands, HAND_NAMES, snap.glove_hand, self._look)
        self._gl.make_current()
        camera = mujoco.MjvCamera()
        camera.type = mujoco.mjtCamera.mjCAMERA_FIXED
        images = []
        for i, (spec, cam_id) in enumerate(zip(self.cameras, self._cam_ids, strict=True)):
            window = (windows[i] if windows is not None else None) or (0, 0, self.width, self.height)
            camera.fixedcamid = cam_id
            if i == 0:  # the geometry is the same for every camera: build it once per frame set
                mujoco.mjv_updateScene(self.model, d, self._option, None, camera, mujoco.mjtCatBit.mjCAT_ALL,
                                       self._scene)
                self._add_decor(capsules)
            else:
                mujoco.mjv_updateCamera(self.model, d, camera, self._scene)
                mujoco.mjv_makeLights(self.model, d, self._scene)  # the headlight sits at the camera
            center, half, bottom, top = gl_frustum(spec.K, window, self._near)
            for glcam in self._scene.camera:
                glcam.frustum_near = self._near
                glcam.frustum_center, glcam.frustum_width = center, half
                glcam.frustum_bottom, glcam.frustum_top = bottom, top
            rect = mujoco.MjrRect(0, 0, window[2], window[3])
            mujoco.mjr_render(rect, self._scene, self._ctx)
            rgb = np.empty((window[3], window[2], 3), np.uint8)
            mujoco.mjr_readPixels(rgb, None, rect, self._ctx)
            images.append(np.flipud(rgb))
        return images

    def close(self) -> None:
        if self._gl is not None:
            self._gl.make_current()
            self._ctx.free()
            self._gl.free()
            self._gl = None
