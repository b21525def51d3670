"""camhub node: trigger the rig at a set rate, publish JPEG images and CameraInfo per camera.

The deployment picks the source (``sim``, ``v4l2``, ``files``) and names the calibration file the
CameraInfo comes from; each trigger carries per-camera readout windows that follow the hands of
the last reconstructed scene (services/camhub/roi.py).
"""

from __future__ import annotations

import asyncio
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from services.camhub.camera_info import camera_info, encode_jpeg, from_calibration
from services.camhub.driver import (
    DeviceRig,
    FileSource,
    FrameSet,
    RigError,
    SimRig,
    SizeMismatchError,
    V4L2Source,
    warm_renderer,
)
from services.camhub.roi import CameraGeometry, RoiParams, full_frame, missing_hand, rig_windows, tracked_points
from services.world.model import camera_specs
from shared import calibration, msgs
from shared.config import ConfigError, Deployment
from shared.keys import CAMERAS
from shared.robots.registry import DEFAULT_ROBOT
from shared.runtime import Node

SOURCES = ("sim", "v4l2", "files")


class CamhubService:
    @dataclass
    class Params:
        source: str = "sim"  # "sim" (rendered by the world), "v4l2" (devices), "files" (recorded session)
        rate_hz: float = 10.0
        jpeg_quality: int = 80
        width: int = 320  # every camera's full image; the calibration must be at this size
        height: int = 240
        calibration: str = ""  # rig calibration file (`xm calibrate`); sim without one: the world's true cameras
        cameras: tuple[str, ...] = ()  # camera names in rig order; default cam0..cam6
        devices: tuple[str, ...] = ()  # v4l2: one device per camera (/dev/v4l/by-id/..., /dev/video2, or 2)
        fps: float = 0.0  # v4l2: frame rate asked of the devices; 0 = rate_hz
        files: tuple[str, ...] = ()  # files: one video file or image folder per camera
        loop: bool = True  # files: start over at the end
        roi: bool = True  # read out windows around the tracked hands; false: full frames always
        roi_margin_m: float = 0.08
        roi_min_px: int = 64
        roi_max_age_s: float = 0.5
        roi_reacquire_every: int = 10
        roi_reacquire_lost_every: int = 2

    # A standby spare's rig thread and the renderer built on it, by its params.
    _prepared: ClassVar[dict[str, tuple[ThreadPoolExecutor, object]]] = {}

    @classmethod
    def prepare(cls, params: Params, deployment: Deployment | None = None) -> None:
        """A standby spare of the simulated rig builds its renderer for the deployment's world
        (task, robot) and draws one frame before it takes over: MuJoCo's import, the model, the
        GL context and the first frame are most of camhub's first trigger. A world on another
        task makes the rig build another renderer at its first frame."""
        if params.source != "sim":
            return
        world = next(iter((deployment.services.get("world", {}) if deployment else {}).values()), {})
        task = str(world.get("task", "assembly"))
        robot = str(world.get("robot", deployment.robot if deployment else DEFAULT_ROBOT))
        worker = ThreadPoolExecutor(1, thread_name_prefix="rig")  # the GL context is current on this thread only
        renderer = worker.submit(warm_renderer, task, params.width, params.height, robot).result()
        cls._prepared[repr(params)] = (worker, renderer)

    def __init__(self, node: Node, params: Params) -> None:
        self.node = node
        self.params = params
        self.names = list(params.cameras) or list(CAMERAS)
        self.cameras, self.intrinsics = self._geometry(params)
        self.roi_params = RoiParams(params.roi_margin_m, params.roi_min_px, params.roi_max_age_s,
                                    params.roi_reacquire_every, params.roi_reacquire_lost_every)
        prepared = self._prepared.pop(repr(params), None)
        # The rig's GL context lives on this thread.
        self.worker = prepared[0] if prepared else ThreadPoolExecutor(1, thread_name_prefix="rig")
        self.rig = self._rig(params, prepared[1] if prepared else None)
        self.pubs = {name: (node.output("image", name), node.output("info", name))
                     for name in self.names}
        # (stamp, tracked keypoints, a hand missing) of the last scene
        self.hands: tuple[float, np.ndarray, bool] | None = None
        self.windows = {c.name: full_frame(c.width, c.height) for c in self.cameras}
        self.tracking = False
        self.triggers = 0
        node.input("scene", self.on_scene)
        node.health_extra = self._health

    # --- configuration ------------------------------------------------------------------
    def _geometry(self, p: Params) -> tuple[list[CameraGeometry], str]:
        if p.source not in SOURCES:
            raise ConfigError(f"camhub source {p.source!r}: expected one of {', '.join(SOURCES)}")
        if p.calibration:
            try:
                rig = calibration.load(p.calibration)
                rig.check_rig({n: (p.width, p.height) for n in self.names}, p.calibration)
            except calibration.CalibrationError as exc:
                raise ConfigError(f"camhub: {exc}") from exc
            return from_calibration(rig, self.names), f"calibration {p.calibration}"
        if p.source != "sim":
            raise ConfigError(f"camhub source {p.source!r} needs calibration = \"path\" (a rig calibration file "
                              "written by `xm calibrate`)")
        truth = {c.name: c for c in camera_specs(p.width, p.height)}
        unknown = [n for n in self.names if n not in truth]
        if unknown:
            raise ConfigError(f"camhub: the simulated rig has no camera(s) {', '.join(unknown)} "
                              f"(it has {', '.join(truth)})")
        return ([CameraGeometry(n, p.width, p.height, truth[n].K, np.zeros(5), truth[n].world_T_cam)
                 for n in self.names], "the world's true cameras (no calibration file given)")

    def _rig(self, p: Params, renderer: object | None = None) -> SimRig | DeviceRig:
        if p.source == "sim":
            return SimRig(self.node.session, self.names, p.width, p.height, renderer=renderer)
        paths, what = (p.devices, "devices") if p.source == "v4l2" else (p.files, "files")
        if len(paths) != len(self.names):
            raise ConfigError(f"camhub source {p.source!r}: {len(paths)} {what} for {len(self.names)} cameras "
                              f"({', '.join(self.names)}); give one per camera, in that order")
        if p.source == "v4l2":
            sources = [V4L2Source(d, p.width, p.height, p.fps or p.rate_hz) for d in paths]
        else:
            sources = [FileSource(f, p.width, p.height, p.loop) for f in paths]
        rig = DeviceRig(self.names, sources, p.width, p.height)
        failures = rig.open_all(self.node.clock.now())
        wrong = [str(f) for f in failures if isinstance(f, SizeMismatchError)]
        if wrong:
            rig.close()
            raise ConfigError("camhub: " + "; ".join(wrong))
        if failures:
            self.node.set_status("degraded", "; ".join(str(f) for f in failures))
        return rig

    # --- inputs -------------------------------------------------------------------------
    def on_scene(self, msg) -> None:
        try:
            points = tracked_points(msg.hand_keypoints, msg.hand_mask)
            missing = missing_hand(msg.hand_mask, len(msg.hand_names)) if len(msg.hand_mask) else False
        except ValueError as exc:
            self.node.stats.count("bad_scene")
            self.node.log.warning("scene ignored: %s", exc)
            return
        self.hands = (msgs.stamp_seconds(msg.header.stamp), points, missing)

    def _next_windows(self, now: float) -> None:
        if not self.params.roi:
            return
        stamp, points, missing = self.hands if self.hands is not None else (-np.inf, None, False)
        self.windows, self.tracking = rig_windows(self.cameras, points, now - stamp, self.triggers, self.roi_params,
                                                  missing)

    # --- main loop ----------------------------------------------------------------------
    async def run(self) -> None:
        by_name = {c.name: c for c in self.cameras}
        async for _ in self.node.clock.ticks(self.params.rate_hz):
            now = self.node.clock.now()
            self._next_windows(now)
            self.triggers += 1
            try:
                frames: FrameSet = await self.node.loop.run_in_executor(self.worker, self.rig.trigger,
                                                                        self.windows, now)
            except RigError as exc:
                self.node.stats.count("trigger_failed")
                self.node.set_status("degraded", str(exc))
                await asyncio.sleep(0.1)  # the world is back within a few ticks of restarting: retry soon
                continue
            if frames.missing:
                self.node.stats.count("camera_missing", n=len(frames.missing))
                self.node.set_status("degraded", "missing: " + ", ".join(frames.missing) + " (reopening)")
            else:
                self.node.set_status("ok")
            encoded = await self.node.loop.run_in_executor(self.worker, encode_all, frames.frames,
                                                           self.params.jpeg_quality)
            for frame, jpeg in zip(frames.frames, encoded, strict=True):
                image_pub, info_pub = self.pubs[frame.name]
                header = msgs.header(frames.stamp, frame.name)
                image_pub.put(msgs.make("sensor_msgs/msg/CompressedImage", header=header, format="jpeg",
                                        data=np.frombuffer(jpeg, np.uint8)))
                info_pub.put(camera_info(header, by_name[frame.name], frame.roi))

    def _health(self) -> dict:
        return {"source": self.params.source, "intrinsics": self.intrinsics, "tracking": self.tracking,
                "roi": {n: list(r) for n, r in self.windows.items()}, "cameras": self.rig.health()}

    async def close(self) -> None:
        await self.node.loop.run_in_executor(self.worker, self.rig.close)
        self.worker.shutdown(wait=False)


def encode_all(frames: list, quality: int) -> list[bytes]:
    return [encode_jpeg(f.image, quality) for f in frames]
