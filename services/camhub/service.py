"""camhub node: trigger the rig at a set rate, publish JPEG images and CameraInfo per camera."""

from __future__ import annotations

import asyncio
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from services.camhub.camera_info import encode_jpeg
from services.camhub.driver import RigError, SimRig
from shared import msgs
from shared.geometry import projection
from shared.runtime import Node


class CamhubService:
    @dataclass
    class Params:
        source: str = "sim"
        rate_hz: float = 10.0
        jpeg_quality: int = 80
        width: int = 320
        height: int = 240

    def __init__(self, node: Node, params: Params) -> None:
        if params.source != "sim":
            raise ValueError(f"camhub source {params.source!r}: only 'sim' is wired in this build")
        self.node = node
        self.params = params
        self.rig = SimRig(node.session, params.width, params.height)
        self.worker = ThreadPoolExecutor(1, thread_name_prefix="rig")  # the rig's GL context lives on this thread
        self.pubs: dict[str, tuple] = {}

    def _publishers(self, name: str) -> tuple:
        if name not in self.pubs:
            self.pubs[name] = (self.node.publisher(f"xm/camhub/{name}/image"),
                               self.node.publisher(f"xm/camhub/{name}/info"))
        return self.pubs[name]

    async def run(self) -> None:
        async for _ in self.node.clock.ticks(self.params.rate_hz):
            try:
                stamp, frames = await self.node.loop.run_in_executor(self.worker, self.rig.trigger)
            except RigError as exc:
                self.node.stats.count("trigger_failed")
                self.node.set_status("degraded", str(exc))
                await asyncio.sleep(0.1)  # the world is back within a few ticks of restarting: retry soon
                continue
            self.node.set_status("ok")
            encoded = await self.node.loop.run_in_executor(self.worker, encode_all, frames, self.params.jpeg_quality)
            for frame, jpeg in zip(frames, encoded, strict=True):
                image_pub, info_pub = self._publishers(frame.name)
                header = msgs.header(stamp, frame.name)
                image_pub.put(msgs.make("sensor_msgs/msg/CompressedImage", header=header, format="jpeg",
                                        data=np.frombuffer(jpeg, np.uint8)))
                info_pub.put(camera_info(header, frame))


    async def close(self) -> None:
        await self.node.loop.run_in_executor(self.worker, self.rig.close)
        self.worker.shutdown(wait=False)


def encode_all(frames: list, quality: int) -> list[bytes]:
    return [encode_jpeg(f.image, quality) for f in frames]


def camera_info(header, frame) -> object:
    h, w = frame.image.shape[:2]
    return msgs.make(
        "sensor_msgs/msg/CameraInfo", header=header, height=h, width=w, distortion_model="plumb_bob",
        d=np.zeros(5), k=frame.K.ravel().astype(float), r=np.eye(3).ravel(),
        p=projection(frame.K, frame.world_T_cam).ravel().astype(float), binning_x=0, binning_y=0,
        roi=msgs.make("sensor_msgs/msg/RegionOfInterest", x_offset=0, y_offset=0, height=0, width=0,
                      do_rectify=False))
