"""Regenerates the robot-board test vectors (run only when the protocol changes on purpose):
python -m shared.protocols.vectors.make_vectors. Tactile vectors: python -m shared.protocols.tactile"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from shared.protocols import robot_board as rb

HERE = Path(__file__).parent


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
    (HERE / "robot_board.json").write_text(json.dumps(board_vectors(), indent=1))
