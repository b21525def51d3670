"""A serial port on the asyncio loop, with reconnection.

Used by every driver (glove, robot) on hardware and in simulation alike: in the sim the port is
a pty hosted by the world. Reads are event driven (``add_reader`` on the port's fd); when the
port vanishes the link closes, retries every ``retry_s`` and reports the gap.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable

import serial

log = logging.getLogger("xm")


class SerialLink:
    def __init__(self, port: str, on_bytes: Callable[[bytes], None], baudrate: int = 3_000_000,
                 retry_s: float = 0.1, on_state: Callable[[bool, float], None] | None = None) -> None:
        self.port = port
        self.baudrate = baudrate
        self.retry_s = retry_s
        self._on_bytes = on_bytes
        self._on_state = on_state  # (connected, gap_seconds)
        self._ser: serial.Serial | None = None
        self._lost_at: float | None = time.monotonic()
        self.connects = 0
        self.disconnects = 0
        self.last_gap_s = 0.0
        self._loop: asyncio.AbstractEventLoop | None = None
        self._closed = False

    @property
    def connected(self) -> bool:
        return self._ser is not None

    async def run(self) -> None:
        """Keep the port open until ``close``; returns only when closed."""
        self._loop = asyncio.get_running_loop()
        while not self._closed:
            if self._ser is None:
                self._try_open()
            await asyncio.sleep(self.retry_s)

    def _try_open(self) -> None:
        try:
            ser = serial.Serial(self.port, self.baudrate, timeout=0, write_timeout=0)
        except (serial.SerialException, OSError):
            return
        self._ser = ser
        self.connects += 1
        gap = time.monotonic() - self._lost_at if self._lost_at is not None else 0.0
        if self.connects > 1:
            self.last_gap_s = gap
            log.warning("serial port back", extra={"fields": {"port": self.port, "gap_s": round(gap, 3)}})
        self._lost_at = None
        self._loop.add_reader(ser.fileno(), self._readable)
        if self._on_state:
            self._on_state(True, gap)

    def _readable(self) -> None:
        try:
            data = self._ser.read(65536)
        except (serial.SerialException, OSError, TypeError):
            self._lose("read failed")
            return
        if data:
            self._on_bytes(data)
        elif self._ser.fileno() is not None:
            # Readable with no data: the other end hung up (pty master closed / USB unplugged).
            self._lose("hang-up")

    def write(self, data: bytes) -> bool:
        if self._ser is None:
            return False
        try:
            self._ser.write(data)
            return True
        except (serial.SerialException, OSError, serial.SerialTimeoutException):
            self._lose("write failed")
            return False

    def _lose(self, why: str) -> None:
        if self._ser is None:
            return
        try:
            self._loop.remove_reader(self._ser.fileno())
        except (ValueError, OSError, TypeError):
            pass
        try:
            self._ser.close()
        except Exception:
            pass
        self._ser = None
        self._lost_at = time.monotonic()
        self.disconnects += 1
        log.warning("serial port lost", extra={"fields": {"port": self.port, "why": why}})
        if self._on_state:
            self._on_state(False, 0.0)

    def stats(self) -> dict:
        return {"connected": self.connected, "connects": self.connects, "disconnects": self.disconnects,
                "last_gap_s": round(self.last_gap_s, 4)}

    def close(self) -> None:
        self._closed = True
        self._lose("closed") if self._ser is not None else None
