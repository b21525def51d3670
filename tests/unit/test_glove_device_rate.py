"""The world's simulated readout module frames at the core's period, window x tick_div / f_clk."""

import numpy as np
import serial

from services.world.devices import GloveDevice
from services.world.sim import TACTILE_REGIONS
from shared.protocols import tactile
from tests.conftest import wait_until


def _received(port: serial.Serial, decoder: tactile.StreamDecoder, kind: type, what: str, device=None) -> list:
    """Waits until at least one message of ``kind`` came through the pty (polling ``device`` meanwhile,
    as the world does every tick); returns those decoded."""
    got: list = []

    def arrived() -> list:
        if device is not None:
            device.poll()
        got.extend(m for m in decoder.feed(port.read(port.in_waiting)) if isinstance(m, kind))
        return got

    return wait_until(arrived, 5.0, what)


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
                    # the host keeps up, as the glove service does: one window, one frame
                    frames += _received(host, decoder, tactile.TactileFrame, f"the frame of the window at {t:.3f} s")
                else:
                    device.poll()
            return frames

        first = run(0.0, 0.2)
        assert np.allclose(np.diff([f.timestamp_us for f in first]), 10_000, atol=1)
        host.write(tactile.encode_write(tactile.REG_WINDOW, 128))  # the host halves the window
        host.flush()
        replies = _received(host, decoder, tactile.RegisterReply, "the reply to the window write", device)
        assert [r.value for r in replies] == [128]
        second = run(0.2, 0.2)
        assert np.allclose(np.diff([f.timestamp_us for f in second[1:]]), 5_000, atol=1)
        assert len(second) >= 2 * len(first) - 2
    finally:
        host.close()
        device.close()
