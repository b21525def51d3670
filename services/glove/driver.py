"""The glove's hardware path: serial port -> protocol decoder -> calibrated pressure.

The same code reads the world's simulated readout module (a pty) and the real radio receiver.
Frames are decoded, calibrated and handed to ``on_frame`` on the serial link's reader thread (a
real-time thread where the OS allows: shared/serial_link.py), so a busy event loop or host does
not hold them up; register replies go to the waiting request on the event loop. On a host with
every core busy the reader also needs the kernel threads that bring it the bytes and the threads
that send what it publishes at real-time priority (shared/realtime.py): the driver raises both.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable

import numpy as np

from services.glove.calibration import Calibration
from services.glove.layout import Layout
from services.glove.sensor_model import nominal_calibration
from shared.protocols import tactile
from shared.realtime import (
    DEFAULT_RT_PRIORITY,
    TTY_WORKER_RT_PRIORITY,
    TtyWorkers,
    lock_memory,
    raise_process_priority,
)
from shared.serial_link import SerialLink

PROCESS_RT_PRIORITY = 5  # the event loop and Zenoh's threads: real time, below the reader
TTY_WORKER_RESCAN_S = 0.1  # the kernel starts new workqueue workers as it needs them; a look costs ~0.1 ms


class RegisterError(RuntimeError):
    """A register access that could not be made or was refused."""


def register_address(name: str) -> int:
    """Address of a register by its spec name (docs/protocols/tactile.md), e.g. "window", "freq3"."""
    by_name = {v: k for k, v in tactile.REGISTER_NAMES.items()}
    if name not in by_name:
        raise RegisterError(f"unknown register {name!r}; known: {', '.join(by_name)}")
    return by_name[name]


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
                 log: logging.Logger, clock: DeviceClock, layout: Layout, calibration_seed: int = 0,
                 rt_priority: int = DEFAULT_RT_PRIORITY, process_rt_priority: int = PROCESS_RT_PRIORITY,
                 tty_worker_rt_priority: int = TTY_WORKER_RT_PRIORITY) -> None:
        if not port:
            raise ValueError("glove: no serial port configured (set port = \"/dev/ttyACM0\" in the deployment)")
        self.calibration = (Calibration.load(calibration_path, layout.mask) if calibration_path
                            else nominal_calibration(calibration_seed, layout))
        self.decoder = tactile.StreamDecoder()
        self.clock = clock
        self.on_frame = on_frame
        self.log = log
        self.last_sequence: int | None = None
        self._pending: dict[int, list[asyncio.Future]] = {}  # register address -> waiting requests
        self._loop: asyncio.AbstractEventLoop | None = None
        self.process_rt_priority = process_rt_priority
        self.tty_workers = TtyWorkers(tty_worker_rt_priority) if tty_worker_rt_priority > 0 else None
        self.link = SerialLink(port, self._on_bytes, baudrate, rt_priority=rt_priority)

    def _on_bytes(self, data: bytes) -> None:  # the reader thread
        for item in self.decoder.feed(data):
            if isinstance(item, tactile.TactileFrame):
                pressure = self.calibration.pressure(item.impedance)
                self.on_frame(item, pressure, self.clock.stamp(item.timestamp_us))
            elif self._loop is not None:
                self._loop.call_soon_threadsafe(self._on_reply, item)

    def _on_reply(self, item: tactile.RegisterReply) -> None:  # the event loop
        waiting = self._pending.get(item.address)
        if waiting:
            fut = waiting.pop(0)
            if not fut.done():
                fut.set_result(item)

    async def register(self, name: str, value: int | None = None, timeout: float = 0.5) -> tactile.RegisterReply:
        """Reads (value None) or writes one configuration register by name; RegisterError when the
        name is unknown, the port is down or the module does not answer within ``timeout``."""
        address = register_address(name)
        fut = asyncio.get_running_loop().create_future()
        self._pending.setdefault(address, []).append(fut)
        try:
            if not self.link.write(tactile.encode_command(address, value)):
                raise RegisterError(f"glove port {self.link.port} is not connected")
            return await asyncio.wait_for(fut, timeout)
        except TimeoutError:
            raise RegisterError(f"no reply for register {name} within {timeout} s") from None
        finally:
            if fut in self._pending.get(address, []):
                self._pending[address].remove(fut)

    async def run(self) -> None:
        self._loop = asyncio.get_running_loop()
        # the GIL ties the reader to every other thread of the process, and Zenoh's threads send what it
        # publishes: none of them may wait behind other processes
        if self.link.rt_priority > 0:
            raise_process_priority("glove", self.log, rt_priority=self.process_rt_priority)
            lock_memory("glove", self.log)
        if self.tty_workers is not None:
            await asyncio.gather(self.link.run(), self._keep_tty_workers_raised())
        else:
            await self.link.run()

    async def _keep_tty_workers_raised(self) -> None:
        """The kernel threads that move received bytes to the reader, at real time (host-wide, once
        per new worker; the first refusal is logged)."""
        workers, warned = self.tty_workers, False
        while True:
            raised = workers.raise_new()
            if raised:
                self.log.info("glove: %d kernel tty workers (kworker/u*) at SCHED_FIFO priority %d", raised,
                              workers.rt_priority)
            elif workers.refused and not warned:
                warned = True
                self.log.warning("glove: the kernel's tty workers keep normal priority (%s): with every core busy "
                                 "frames reach the reader tens of ms late", workers.refused)
            await asyncio.sleep(TTY_WORKER_RESCAN_S)

    @property
    def tty_workers_raised(self) -> int:
        return self.tty_workers.raised if self.tty_workers is not None else 0

    def close(self) -> None:
        self.link.close()
