"""The serial link over a real pty: bytes both ways, hang-up detection, reconnection and gap."""

from __future__ import annotations

import asyncio

import serial

from services.world.pty_device import PtyDevice
from shared.serial_link import SerialLink


async def _wait(cond, timeout: float = 2.0) -> bool:
    for _ in range(int(timeout / 0.01)):
        if cond():
            return True
        await asyncio.sleep(0.01)
    return False


def test_bytes_both_ways_and_reconnect_after_port_vanishes(tmp_path):
    async def go() -> None:
        link_path = tmp_path / "dev"
        got = bytearray()
        states: list[bool] = []
        dev = PtyDevice(link_path)
        link = SerialLink(str(link_path), got.extend, retry_s=0.02, on_state=lambda up, gap: states.append(up))
        runner = asyncio.ensure_future(link.run())
        assert await _wait(lambda: link.connected)
        dev.write(bytes(range(256)))
        assert await _wait(lambda: len(got) == 256)
        assert bytes(got) == bytes(range(256))
        assert link.write(b"\x00\xffcmd")
        sent = bytearray()
        assert await _wait(lambda: sent.extend(dev.read()) or bytes(sent) == b"\x00\xffcmd")
        dev.close()  # the device disappears
        assert await _wait(lambda: not link.connected)
        assert link.write(b"lost") is False
        dev = PtyDevice(link_path)  # and comes back
        assert await _wait(lambda: link.connected, 1.0), "must reconnect within 1 s"
        assert link.last_gap_s > 0
        dev.write(b"again")
        assert await _wait(lambda: bytes(got).endswith(b"again"))
        assert states == [True, False, True] and link.disconnects == 1
        link.close()
        runner.cancel()
        dev.close()

    asyncio.run(go())


def test_the_simulated_device_queues_what_the_pty_cannot_take_and_counts_only_fifo_overflow(tmp_path):
    """A pty holds ~18 kB; the device keeps the rest in its FIFO, in order, and drops (and counts)
    only what overflows that."""
    dev = PtyDevice(tmp_path / "dev", fifo_bytes=64 * 1024)
    port = serial.Serial(str(tmp_path / "dev"), timeout=0.2)
    data = bytes(i % 251 for i in range(60 * 1024))
    try:
        assert dev.write(data) == len(data) and dev.backlog > 0 and dev.dropped_bytes == 0
        got = bytearray()
        while len(got) < len(data):
            chunk = port.read(65536)
            assert chunk, f"stalled after {len(got)} bytes"
            got += chunk
            dev.flush()
        assert bytes(got) == data and dev.backlog == 0
        dev.write(bytes(200 * 1024))  # nobody reads: the pty fills, then the FIFO, then bytes drop
        assert dev.backlog == 64 * 1024 and dev.dropped_bytes > 0
        assert 180 * 1024 <= dev.dropped_bytes + dev.backlog <= 200 * 1024  # the rest went into the pty
    finally:
        port.close()
        dev.close()
