"""Regenerates the protocol test vectors (run only when the protocol changes on purpose):
python -m shared.protocols.vectors.make_vectors"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from shared.protocols import robot_board as rb
from shared.protocols import tactile

HERE = Path(__file__).parent


def tactile_vectors() -> list[dict]:
    rng = np.random.default_rng(7)
    cases = []
    for i, scale in enumerate((1.0, 1e-3, 250.0)):
        z = (rng.normal(0, scale, (16, 16)) + 1j * rng.normal(scale, scale, (16, 16))).astype(np.complex64)
        z = tactile.quantize(z)  # vectors hold exactly representable values
        imu = None if i != 1 else np.array([[0.0, 0.0, 9.81, 0.01, -0.02, 0.5]], np.float32)
        frame = tactile.TactileFrame(1000 + i, 123_456_789 + i, z, imu)
        cases.append({"sequence": frame.sequence, "timestamp_us": frame.timestamp_us,
                      "real": z.real.ravel().tolist(), "imag": z.imag.ravel().tolist(),
                      "imu": None if imu is None else imu.tolist(), "bytes": tactile.encode_frame(frame).hex()})
    cases.append({"register_write": [0x0004, 4096], "bytes": tactile.encode_write(0x0004, 4096).hex()})
    cases.append({"register_reply": [0x0000, 0x58540001, 0], "bytes": tactile.encode_reply(0x0000, 0x58540001).hex()})
    return cases


def board_vectors() -> list[dict]:
    n = 10
    cmd = rb.CommandFrame(42, np.array([1] * 9 + [4], np.uint8), np.linspace(-0.1, 0.1, n), np.zeros(n),
                          np.full(n, 0.5), np.full(n, 100.0), np.full(n, 5.0))
    fb = rb.FeedbackFrame(7, 1_000_000, rb.WATCHDOG_EXPIRED, np.linspace(0, 0.3, n), np.full(n, -0.25),
                          np.full(n, 1.5), 989_000)
    return [{"command": {"sequence": 42, "mode": cmd.mode.tolist(), "position": cmd.position.tolist(),
                         "velocity": cmd.velocity.tolist(), "effort": cmd.effort.tolist(),
                         "stiffness": cmd.stiffness.tolist(), "damping": cmd.damping.tolist()},
             "bytes": rb.encode_command(cmd).hex()},
            {"feedback": {"sequence": 7, "timestamp_us": 1_000_000, "last_command_us": 989_000, "flags": 1,
                          "position": fb.position.tolist(),
                          "velocity": fb.velocity.tolist(), "current": fb.current.tolist()},
             "bytes": rb.encode_feedback(fb).hex()},
            {"config": {"watchdog_timeout_us": 10_000}, "bytes": rb.encode_config(rb.ConfigFrame(10_000)).hex()}]


if __name__ == "__main__":
    (HERE / "tactile.json").write_text(json.dumps(tactile_vectors(), indent=1))
    (HERE / "robot_board.json").write_text(json.dumps(board_vectors(), indent=1))
