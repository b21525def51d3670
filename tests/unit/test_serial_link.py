"""The serial link over a real pty: bytes both ways, hang-up detection, reconnection and gap."""

from __future__ import annotations

import asyncio

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
