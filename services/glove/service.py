"""glove node: read the readout module over serial, decode, calibrate, publish pressure.

The glove's layout (which crossing is which sensor's cell) is its cell map file, the ``cellmap``
parameter (services/glove/layout.py). A cell map that is missing, malformed or inconsistent is
refused at start: the service opens no port and publishes nothing, its status is ``error`` with the
file and the problem, @health's ``layout`` carries the same, and ``bad_cellmap`` is counted."""

from __future__ import annotations

import asyncio
import functools
from dataclasses import dataclass

import numpy as np

from services.glove import layout as glove_layout
from services.glove.driver import DeviceClock, GloveDriver, RegisterError
from services.glove.layout import CellMapError, Layout
from shared import msgs
from shared.protocols import tactile
from shared.runtime import Node


@functools.lru_cache(maxsize=64)
def cell_mask(layout: Layout, tx_mask: int, rx_mask: int) -> np.ndarray:
    """Flat 0/1 mask of the glove's cells carried by a frame (cells of lines not read: masked)."""
    carried = np.zeros(layout.mask.size, np.uint8)
    carried[tactile.cell_index(tx_mask, rx_mask)] = 1
    mask = layout.mask.ravel().astype(np.uint8) & carried
    mask.flags.writeable = False  # shared between frames
    return mask


class GloveService:
    @dataclass
    class Params:
        port: str = ""
        baudrate: int = 3_000_000
        calibration: str = ""  # JSON from `xm glove calibrate`; empty: the simulated glove's factory one
        calibration_seed: int = -1  # which simulated glove's factory calibration (-1: by hand, 0 left, 1 right)
        cellmap: str = ""  # the glove's cell map (`xm skin glove`); empty: models/skin/glove_cellmap.json
        publish_raw: bool = False
        publish_imu: bool = False
        # SCHED_FIFO priority of the serial reader thread, which also decodes and publishes (0: normal
        # priority); refused by the OS -> nice -10 or normal priority, logged (shared/realtime.py).
        reader_rt_priority: int = 10
        # SCHED_FIFO priority of the service's other threads (event loop, Zenoh's), which send what the
        # reader publishes and share its GIL (0: nice -10); only while the reader is real-time.
        process_rt_priority: int = 5
        # SCHED_FIFO priority for the kernel's unbound workqueue workers, which bring every received byte
        # to the reader (host-wide; 0: leave the kernel's threads alone).
        tty_worker_rt_priority: int = 9

    def __init__(self, node: Node, params: Params) -> None:
        self.node = node
        self.hand = node.instance
        self.tactile_pub = node.output("tactile")
        self.raw_pub = node.output("raw") if params.publish_raw else None
        self.imu_pub = node.output("imu") if params.publish_imu else None
        node.queryable("register", self.cmd_register)
        node.health_extra = self._health
        self.driver: GloveDriver | None = None
        self.layout: Layout | None = None
        self.layout_error = ""
        try:
            self.layout = glove_layout.load(params.cellmap)
        except CellMapError as exc:
            self.layout_error = str(exc)
            node.stats.count("bad_cellmap")
            node.log.error("%s; the glove publishes nothing (write one with `xm skin glove`, docs/skin.md)", exc)
            node.set_status("error", str(exc))
            return
        seed = params.calibration_seed if params.calibration_seed >= 0 else (1 if self.hand == "right" else 0)
        clock = DeviceClock(node.clock.now, sim=node.clock.mode == "sim")
        self.driver = GloveDriver(params.port, params.baudrate, params.calibration, self._on_frame, node.log,
                                  clock, self.layout, calibration_seed=seed, rt_priority=params.reader_rt_priority,
                                  process_rt_priority=params.process_rt_priority,
                                  tty_worker_rt_priority=params.tty_worker_rt_priority)

    def _health(self) -> dict:
        layout = self.layout.summary() if self.layout is not None else {"error": self.layout_error}
        if self.driver is None:
            return {"layout": layout}
        return {"layout": layout, "link": self.driver.link.stats(), "decoder": dict(self.driver.decoder.stats),
                "tty_workers_raised": self.driver.tty_workers_raised}

    def _on_frame(self, frame, pressure: np.ndarray, stamp: float) -> None:  # the serial reader thread
        header = msgs.header(stamp, f"glove_{self.hand}")
        mask = cell_mask(self.layout, frame.tx_mask, frame.rx_mask)
        self.tactile_pub.put(msgs.make(
            "xm_msgs/msg/Tactile", header=header, hand=self.hand, rows=16, cols=16,
            pressure=np.where(mask, pressure.ravel(), 0.0).astype(np.float32), mask=mask, sequence=frame.sequence))
        if self.raw_pub is not None:
            z = frame.impedance.ravel()
            self.raw_pub.put(msgs.make("xm_msgs/msg/TactileRaw", header=header, hand=self.hand, rows=16, cols=16,
                                       real=z.real.astype(np.float32), imag=z.imag.astype(np.float32),
                                       sequence=frame.sequence))
        if self.imu_pub is not None and frame.imu is not None and len(frame.imu):
            imu = np.asarray(frame.imu, np.float32)
            self.imu_pub.put(msgs.make("xm_msgs/msg/Imu", header=header, hand=self.hand,
                                       accel=imu[:, :3].ravel(), gyro=imu[:, 3:6].ravel()))

    async def cmd_register(self, request: dict) -> dict:
        """``{"name": "window"}`` reads, ``{"name": "window", "value": 128}`` writes a register of the
        readout module (names in docs/protocols/tactile.md)."""
        name, value = request.get("name"), request.get("value")
        if not isinstance(name, str) or (value is not None and (not isinstance(value, int) or value < 0)):
            return {"ok": False, "error": "request {\"name\": str, \"value\": non-negative int (omit to read)}"}
        if self.driver is None:
            return {"ok": False, "error": f"no readout module open: {self.layout_error}"}
        try:
            reply = await self.driver.register(name, value)
        except RegisterError as exc:
            self.node.stats.count("register_error")
            return {"ok": False, "error": str(exc)}
        status = {tactile.REPLY_OK: "ok", tactile.REPLY_BAD_ADDRESS: "bad_address",
                  tactile.REPLY_READ_ONLY: "read_only"}.get(reply.status, str(reply.status))
        return {"ok": reply.status == tactile.REPLY_OK, "name": name, "address": reply.address,
                "value": reply.value, "status": status}

    async def run(self) -> None:
        if self.driver is None:  # a refused cell map: stay up and say so in @health
            await asyncio.Event().wait()
        else:
            await self.driver.run()

    async def close(self) -> None:
        if self.driver is not None:
            self.driver.close()
        await asyncio.sleep(0)
