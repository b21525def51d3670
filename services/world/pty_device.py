"""A simulated serial device: a pty whose slave end appears at a fixed path for the driver.

The world writes the device's bytes to the master end and reads what the driver sends; the
driver opens the symlinked slave with pyserial exactly as it would open /dev/ttyUSB0.

A pty holds only ~18 kB, 17 ms of a glove at 1 kHz: a reader late by more than that would lose
bytes, where a USB device would just wait to be polled with its own FIFO filling. So bytes the pty
cannot take wait in a device-side FIFO of ``fifo_bytes`` and go out with the next write or read;
only what overflows that FIFO is dropped (and counted), like a device whose host stopped polling.
"""

from __future__ import annotations

import errno
import os
import pty
import termios
import tty
from pathlib import Path

DEFAULT_FIFO_BYTES = 256 * 1024  # ~0.24 s of a glove at 1 kHz


class PtyDevice:
    def __init__(self, link: str | Path, fifo_bytes: int = DEFAULT_FIFO_BYTES) -> None:
        self.link = Path(link)
        self.fifo_bytes = fifo_bytes
        self._fifo = bytearray()
        self.fifo_peak = 0
        self.master, self._slave = pty.openpty()
        tty.setraw(self._slave)  # no echo, no line discipline: bytes pass unchanged
        attrs = termios.tcgetattr(self._slave)
        attrs[3] &= ~termios.ECHO
        termios.tcsetattr(self._slave, termios.TCSANOW, attrs)
        os.set_blocking(self.master, False)
        self.slave_path = os.ttyname(self._slave)
        self.link.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.link.with_suffix(".tmp")
        tmp.unlink(missing_ok=True)
        tmp.symlink_to(self.slave_path)
        tmp.replace(self.link)  # atomic: a driver never sees a half-made link
        self.dropped_bytes = 0

    @property
    def slave(self) -> int:
        """The device's own fd of the slave end: it keeps the pty open while no host has it."""
        return self._slave

    def write(self, data: bytes) -> int:
        """Non-blocking; returns the bytes accepted (sent or queued in the device FIFO); what overflows
        the FIFO is dropped and counted in ``dropped_bytes``."""
        if self._fifo:
            self.flush()
        if self._fifo:  # still backed up: queue behind what waits, in order
            n = max(0, min(len(data), self.fifo_bytes - len(self._fifo)))
            self._fifo += data[:n]
            self.dropped_bytes += len(data) - n
            self.fifo_peak = max(self.fifo_peak, len(self._fifo))
            return n
        sent = self._send(data)
        if sent < len(data):
            rest = data[sent:sent + self.fifo_bytes]
            self._fifo += rest
            self.fifo_peak = max(self.fifo_peak, len(self._fifo))
            self.dropped_bytes += len(data) - sent - len(rest)
            return sent + len(rest)
        return sent

    def flush(self) -> None:
        """Send what waits in the device FIFO, as far as the pty takes it."""
        if self._fifo:
            del self._fifo[:self._send(bytes(self._fifo))]

    @property
    def backlog(self) -> int:
        return len(self._fifo)

    def _send(self, data: bytes) -> int:
        try:
            return os.write(self.master, data)
        except BlockingIOError:
            return 0
        except OSError as exc:
            if exc.errno != errno.EIO:  # EIO: nobody has the slave open
                raise
            return len(data)  # nobody listening: bytes go nowhere, as on a cable with no host

    def read(self, limit: int = 65536) -> bytes:
        if self._fifo:
            self.flush()
        try:
            return os.read(self.master, limit)
        except (BlockingIOError, OSError):
            return b""

    def close(self) -> None:
        for fd in (self.master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass
        if self.link.is_symlink():
            self.link.unlink()
