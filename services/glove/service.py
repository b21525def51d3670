"""glove node: read the readout module over serial, decode, calibrate, publish pressure."""

from __future__ import annotations

import asyncio
from dataclasses import dataclass

import numpy as np

from services.glove.driver import DeviceClock, GloveDriver
from services.glove.layout import CELL_MASK
from shared import msgs
from shared.runtime import Node


class GloveService:
    @dataclass
    class Params:
        port: str = ""
        baudrate: int = 3_000_000
        calibration: str = ""  # JSON from `xm glove calibrate`; empty: the simulated glove's factory one
        calibration_seed: int = -1  # which simulated glove's factory calibration (-1: by hand, 0 left, 1 right)
        publish_raw: bool = False
        publish_imu: bool = False

    def __init__(self, node: Node, params: Params) -> None:
        self.node = node
        self.hand = node.instance
        seed = params.calibration_seed if params.calibration_seed >= 0 else (1 if self.hand == "right" else 0)
        clock = DeviceClock(node.clock.now, sim=node.clock.mode == "sim")
        self.driver = GloveDriver(params.port, params.baudrate, params.calibration, self._on_frame, node.log,
                                  clock, calibration_seed=seed)
        self.tactile_pub = node.publisher("tactile")
        self.raw_pub = node.publisher("raw") if params.publish_raw else None
        self.imu_pub = node.publisher("imu") if params.publish_imu else None
        self.mask = CELL_MASK.astype(np.uint8).ravel()
        node.health_extra = lambda: {"link": self.driver.link.stats(), "decoder": dict(self.driver.decoder.stats)}

    def _on_frame(self, frame, pressure: np.ndarray, stamp: float) -> None:
        header = msgs.header(stamp, f"glove_{self.hand}")
        self.tactile_pub.put(msgs.make(
            "xm_msgs/msg/Tactile", header=header, hand=self.hand, rows=16, cols=16,
            pressure=pressure.astype(np.float32).ravel(), mask=self.mask, sequence=frame.sequence))
        if self.raw_pub is not None:
            z = frame.impedance.ravel()
            self.raw_pub.put(msgs.make("xm_msgs/msg/TactileRaw", header=header, hand=self.hand, rows=16, cols=16,
                                       real=z.real.astype(np.float32), imag=z.imag.astype(np.float32),
                                       sequence=frame.sequence))
        if self.imu_pub is not None and frame.imu is not None and len(frame.imu):
            imu = np.asarray(frame.imu, np.float32)
            self.imu_pub.put(msgs.make("xm_msgs/msg/Imu", header=header, hand=self.hand,
                                       accel=imu[:, :3].ravel(), gyro=imu[:, 3:6].ravel()))

    async def run(self) -> None:
        await self.driver.run()

    async def close(self) -> None:
        self.driver.close()
        await asyncio.sleep(0)
