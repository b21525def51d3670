"""The world's simulated readout module frames at the core's period, window x tick_div / f_clk."""

import time

import numpy as np
import serial

from services.world.devices import GloveDevice
from services.world.sim import TACTILE_REGIONS
from shared.protocols import tactile


def _frames(port: serial.Serial, decoder: tactile.StreamDecoder) -> list:
    time.sleep(0.002)  # through the pty
    return [m for m in decoder.feed(port.read(port.in_waiting)) if isinstance(m, tactile.TactileFrame)]


def test_frame_period_follows_the_window_and_tick_div_registers(tmp_path):
    device = GloveDevice(str(tmp_path / "glove"), "left", rate_hz=100.0)
    host = serial.Serial(str(tmp_path / "glove"), timeout=0.2)
    decoder = tactile.StreamDecoder()
    try:
        regs = device.registers.values
        assert regs[tactile.REG_WINDOW] * regs[tactile.REG_TICK_DIV] == tactile.CORE_CLOCK_HZ // 100
        forces = np.zeros(len(TACTILE_REGIONS))

        def run(t0: float, seconds: float) -> list:
            frames = []
            for t in t0 + np.arange(int(round(seconds * 1000))) * 1e-3:  # world ticks of 1 ms
                if device.due(t):
                    device.emit(t, forces)
                    frames += _frames(host, decoder)  # the host keeps up, as the glove service does
                else:
                    device.poll()
            return frames

        first = run(0.0, 0.2)
        assert np.allclose(np.diff([f.timestamp_us for f in first]), 10_000, atol=1)
        host.write(tactile.encode_write(tactile.REG_WINDOW, 128))  # the host halves the window
        host.flush()
        time.sleep(0.05)  # through the pty
        device.poll()
        replies = [m for m in decoder.feed(host.read(64)) if isinstance(m, tactile.RegisterReply)]
        assert replies and replies[0].value == 128
        second = run(0.2, 0.2)
        assert np.allclose(np.diff([f.timestamp_us for f in second[1:]]), 5_000, atol=1)
        assert len(second) >= 2 * len(first) - 2
    finally:
        host.close()
        device.close()
