"""The glove's hardware path: serial port -> protocol decoder -> calibrated pressure.

The same code reads the world's simulated readout module (a pty) and the real radio receiver.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import numpy as np

from services.glove.calibration import Calibration
from services.glove.sensor_model import nominal_calibration
from shared.protocols import tactile
from shared.serial_link import SerialLink


class DeviceClock:
    """Maps device microseconds to the deployment clock: the least-delayed sample defines the offset."""

    def __init__(self, host_now: Callable[[], float], sim: bool) -> None:
        self.host_now = host_now
        self.sim = sim  # in simulation the device counts simulated time itself
        self.offset: float | None = None

    def stamp(self, device_us: int) -> float:
        t_dev = device_us * 1e-6
        if self.sim:
            return t_dev
        candidate = self.host_now() - t_dev
        if self.offset is None or candidate < self.offset:
            self.offset = candidate
        return t_dev + self.offset


class GloveDriver:
    def __init__(self, port: str, baudrate: int, calibration_path: str,
                 on_frame: Callable[[tactile.TactileFrame, np.ndarray, float], None],
                 log: logging.Logger, clock: DeviceClock, calibration_seed: int = 0) -> None:
        if not port:
            raise ValueError("glove: no serial port configured (set port = \"/dev/ttyACM0\" in the deployment)")
        self.calibration = (Calibration.load(calibration_path) if calibration_path
                            else nominal_calibration(calibration_seed))
        self.decoder = tactile.StreamDecoder()
        self.clock = clock
        self.on_frame = on_frame
        self.log = log
        self.last_sequence: int | None = None
        self.link = SerialLink(port, self._on_bytes, baudrate)

    def _on_bytes(self, data: bytes) -> None:
        for item in self.decoder.feed(data):
            if isinstance(item, tactile.TactileFrame):
                pressure = self.calibration.pressure(item.impedance)
                self.on_frame(item, pressure, self.clock.stamp(item.timestamp_us))

    async def run(self) -> None:
        await self.link.run()

    def close(self) -> None:
        self.link.close()
