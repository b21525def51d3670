"""The serial link over a real pty: bytes both ways, hang-up detection, reconnection and gap."""

from __future__ import annotations

import asyncio

import serial

from services.world.pty_device import PtyDevice
from shared.serial_link import SerialLink
from tests.conftest import wait_until_async

# Generous: how fast it reconnects is bench/devices.py's figure, not this test's.
TIMEOUT = 10.0


def test_bytes_both_ways_and_reconnect_after_port_vanishes(tmp_path):
    async def go() -> None:
        link_path = tmp_path / "dev"
        got = bytearray()
        states: list[bool] = []
        dev = PtyDevice(link_path)
        link = SerialLink(str(link_path), got.extend, retry_s=0.02, on_state=lambda up, gap: states.append(up))
        runner = asyncio.ensure_future(link.run())
        await wait_until_async(lambda: link.connected, TIMEOUT, "the link to connect")
        dev.write(bytes(range(256)))
        await wait_until_async(lambda: len(got) >= 256, TIMEOUT, "256 bytes from the device")
        assert bytes(got) == bytes(range(256))
        assert link.write(b"\x00\xffcmd")
        sent = bytearray()
        await wait_until_async(lambda: sent.extend(dev.read()) or len(sent) >= 5, TIMEOUT, "the command at the device")
        assert bytes(sent) == b"\x00\xffcmd"
        dev.close()  # the device disappears
        await wait_until_async(lambda: not link.connected, TIMEOUT, "the link to see the hang-up")
        assert link.write(b"lost") is False
        dev = PtyDevice(link_path)  # and comes back
        await wait_until_async(lambda: link.connected, TIMEOUT, "the link to reconnect")
        assert link.last_gap_s > 0
        dev.write(b"again")
        await wait_until_async(lambda: len(got) >= 256 + 5, TIMEOUT, "the bytes after reconnection")
        assert bytes(got[256:]) == b"again"
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


def test_a_full_port_refuses_a_frame_at_once_and_never_garbles_one(tmp_path):
    """Nobody reads the device: writes fill the pty, then are refused and counted without waiting (a
    real-time command thread must not spin on a full port). Once the device drains, what it got is
    whole frames, in order: the tail of a frame the port took in part went out first."""

    async def go() -> None:
        dev = PtyDevice(tmp_path / "dev")
        link = SerialLink(str(tmp_path / "dev"), lambda data: None, retry_s=0.02)
        runner = asyncio.ensure_future(link.run())
        await wait_until_async(lambda: link.connected, TIMEOUT, "the link to connect")
        frame = lambda i: b"<" + bytes([i % 256]) * 997 + b">"  # noqa: E731
        accepted = [i for i in range(200) if link.write(frame(i))]
        assert link.writes_refused > 0 and len(accepted) < 200
        assert link.stats()["writes_refused"] == link.writes_refused
        got = bytearray()
        await wait_until_async(lambda: got.extend(dev.read()) or link.write(frame(1000)), TIMEOUT,
                               "the port to take a frame again")
        await wait_until_async(lambda: got.extend(dev.read()) or got.endswith(frame(1000)), TIMEOUT,
                               "the last frame at the device")
        assert bytes(got) == b"".join(frame(i) for i in [*accepted, 1000])  # whole, in order, no refused part
        link.close()
        runner.cancel()
        dev.close()

    asyncio.run(go())
