"""A simulated serial device: a pty whose slave end appears at a fixed path for the driver.

The world writes the device's bytes to the master end and reads what the driver sends; the
driver opens the symlinked slave with pyserial exactly as it would open /dev/ttyUSB0.
"""

from __future__ import annotations

import errno
import os
import pty
import termios
import tty
from pathlib import Path


class PtyDevice:
    def __init__(self, link: str | Path) -> None:
        self.link = Path(link)
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

    def write(self, data: bytes) -> int:
        """Non-blocking; bytes the kernel buffer cannot take are dropped and counted (like a UART FIFO)."""
        try:
            n = os.write(self.master, data)
        except BlockingIOError:
            n = 0
        except OSError as exc:
            if exc.errno != errno.EIO:  # EIO: nobody has the slave open
                raise
            n = len(data)  # nobody listening: bytes go nowhere, as on a cable with no host
        self.dropped_bytes += len(data) - n
        return n

    def read(self, limit: int = 65536) -> bytes:
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
