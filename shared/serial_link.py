"""A serial port read by its own thread, with reconnection.

Used by every driver (glove, robot) on hardware and in simulation alike: in the sim the port is
a pty hosted by the world. A dedicated reader thread blocks on the port and hands each bulk read
(up to ``READ_BYTES``) to ``on_bytes`` on that thread, asking for real-time scheduling first
(shared/realtime.py): a reader on the event loop waits behind every other task of the service
and, on a busy host, behind every other process, and a pty holds only ~18 kB (17 ms of a glove
at 1 kHz), so frames were lost. ``on_bytes`` must therefore be thread-safe (hand asyncio work to
the loop with ``call_soon_threadsafe``). When the port vanishes the link closes, the event loop
retries every ``retry_s`` and reports the gap through ``on_state`` (called on the loop).
"""

from __future__ import annotations

import asyncio
import logging
import os
import select
import threading
import time
from collections.abc import Callable

import serial

from shared.realtime import DEFAULT_RT_PRIORITY, raise_priority

log = logging.getLogger("xm")
READ_BYTES = 1 << 20
POLL_S = 0.2  # how often a blocked reader looks at the closed flag


class SerialLink:
    def __init__(self, port: str, on_bytes: Callable[[bytes], None], baudrate: int = 3_000_000,
                 retry_s: float = 0.1, on_state: Callable[[bool, float], None] | None = None,
                 rt_priority: int = DEFAULT_RT_PRIORITY) -> None:
        self.port = port
        self.baudrate = baudrate
        self.retry_s = retry_s
        self.rt_priority = rt_priority
        self._on_bytes = on_bytes
        self._on_state = on_state  # (connected, gap_seconds), on the event loop
        self._ser: serial.Serial | None = None
        self._lock = threading.Lock()
        self._write_lock = threading.Lock()
        self._unsent = b""  # the tail of a frame the port took in part
        self.writes_refused = 0
        self._lost_at: float | None = time.monotonic()
        self.connects = 0
        self.disconnects = 0
        self.last_gap_s = 0.0
        self.reads = 0
        self.bytes_read = 0
        self.max_read = 0  # the largest single read: how far the reader fell behind at worst
        self.callback_errors = 0
        self.priority = "not started"
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
        with self._lock, self._write_lock:
            self._ser, self._unsent = ser, b""  # a frame's tail for the old port would garble the new one
        self.connects += 1
        gap = time.monotonic() - self._lost_at if self._lost_at is not None else 0.0
        if self.connects > 1:
            self.last_gap_s = gap
            log.warning("serial port back", extra={"fields": {"port": self.port, "gap_s": round(gap, 3)}})
        self._lost_at = None
        threading.Thread(target=self._read_loop, args=(ser,), name=f"serial-reader {self.port}", daemon=True).start()
        if self._on_state:
            self._on_state(True, gap)

    # Reader thread: block on the port, hand every read over at once.
    def _read_loop(self, ser: serial.Serial) -> None:
        self.priority = raise_priority(f"serial reader {self.port}", log, self.rt_priority)
        fd = ser.fileno()
        while self._ser is ser:
            try:
                ready, _, _ = select.select([fd], [], [], POLL_S)
                if not ready:
                    continue
                data = os.read(fd, READ_BYTES)
            except (OSError, ValueError, TypeError):  # EIO after hang-up, or closed under us
                self._lose(ser, "read failed")
                return
            if not data:  # readable with no data: the other end hung up (pty master closed / USB unplugged)
                self._lose(ser, "hang-up")
                return
            self.reads += 1
            self.bytes_read += len(data)
            self.max_read = max(self.max_read, len(data))
            try:
                self._on_bytes(data)
            except Exception:  # a decoder bug must not end the reader
                self.callback_errors += 1
                log.exception("serial data handler failed", extra={"fields": {"port": self.port}})

    def write(self, data: bytes) -> bool:
        """Hands ``data`` to the port without waiting; False when it could not take all of it.

        A port whose buffer is full (the device or, in the sim, the world is not reading) takes what
        fits: the rest of a frame it took in part goes out first at the next write, and a frame it
        cannot start is dropped and counted (``writes_refused``), since the next command supersedes
        it. pyserial's own non-blocking write retries a full port in a loop: a real-time command
        thread spinning there kept the reading side from the CPU it needed to drain the port."""
        ser = self._ser
        if ser is None:
            return False
        with self._write_lock:
            try:
                if self._unsent:
                    self._unsent = self._unsent[os.write(ser.fileno(), self._unsent):]
                    if self._unsent:
                        self.writes_refused += 1
                        return False
                sent = os.write(ser.fileno(), data)
            except BlockingIOError:
                self.writes_refused += 1
                return False
            except (OSError, ValueError, TypeError):  # hang-up, or closed under us
                self._unsent = b""
                failed = True
            else:
                self._unsent, failed = data[sent:], False
        if failed:
            self._lose(ser, "write failed")  # outside the write lock: _try_open takes both
        return not failed

    def _lose(self, ser: serial.Serial, why: str) -> None:
        """Close ``ser`` if it is still the open port (any thread)."""
        with self._lock:
            if self._ser is not ser:
                return
            self._ser = None
            self._lost_at = time.monotonic()
            self.disconnects += 1
        try:
            ser.close()
        except Exception:
            pass
        log.warning("serial port lost", extra={"fields": {"port": self.port, "why": why}})
        if self._on_state and self._loop is not None:
            try:
                self._loop.call_soon_threadsafe(self._on_state, False, 0.0)
            except RuntimeError:  # loop closed at shutdown
                pass

    def stats(self) -> dict:
        return {"connected": self.connected, "connects": self.connects, "disconnects": self.disconnects,
                "last_gap_s": round(self.last_gap_s, 4), "reads": self.reads, "bytes_read": self.bytes_read,
                "max_read_bytes": self.max_read, "callback_errors": self.callback_errors,
                "writes_refused": self.writes_refused,
                "reader_priority": self.priority}

    def close(self) -> None:
        self._closed = True
        ser = self._ser
        if ser is not None:
            self._lose(ser, "closed")
