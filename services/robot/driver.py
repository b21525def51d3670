"""The control board's hardware path: the serial link, command encoding and feedback decoding.

Feedback is decoded on the link's reader thread (shared/serial_link.py); ``send`` and ``configure``
are called from the service's command thread."""

from __future__ import annotations

import logging

import numpy as np

from services.robot.safety import Limits
from shared.protocols import robot_board as rb
from shared.realtime import DEFAULT_RT_PRIORITY
from shared.serial_link import SerialLink


class BoardDriver:
    def __init__(self, port: str, baudrate: int, joint_names: list[str], log: logging.Logger,
                 rt_priority: int = DEFAULT_RT_PRIORITY) -> None:
        if not port:
            raise ValueError("robot: no serial port configured (set port = \"/dev/ttyUSB0\" in the deployment)")
        self.joint_names = joint_names
        self.log = log
        self.decoder = rb.StreamDecoder()
        self.feedback: rb.FeedbackFrame | None = None
        self.sequence = 0
        self.config_sequence = 0
        self.link = SerialLink(port, self._on_bytes, baudrate, on_state=self._on_state, rt_priority=rt_priority)

    @property
    def watchdog_state(self) -> str:
        if self.feedback is None:
            return "unknown"
        return "braking" if self.feedback.watchdog_expired else "ok"

    def _on_state(self, connected: bool, gap: float) -> None:
        if not connected:
            self.feedback = None  # stale: never command from a state we cannot see

    def _on_bytes(self, data: bytes) -> None:
        for msg in self.decoder.feed(data):
            if isinstance(msg, rb.FeedbackFrame) and len(msg.position) == len(self.joint_names):
                self.feedback = msg

    def send(self, mode: np.ndarray, position: np.ndarray, velocity: np.ndarray, effort: np.ndarray) -> bool:
        n = len(self.joint_names)
        zeros = np.zeros(n)
        frame = rb.CommandFrame(self.sequence, mode.astype(np.uint8), position, velocity, effort, zeros, zeros)
        self.sequence += 1
        return self.link.write(rb.encode_command(frame))

    def send_plan(self, mode: np.ndarray, position: np.ndarray, velocity: np.ndarray, effort: np.ndarray,
                  spacing_s: float) -> bool:
        """A plan frame: ``position`` and ``velocity`` (knots, n), the first row the command in force
        now, the others ``spacing_s`` apart."""
        zeros = np.zeros(len(self.joint_names))
        command = rb.CommandFrame(self.sequence, mode.astype(np.uint8), position[0], velocity[0], effort, zeros, zeros)
        plan = rb.PlanFrame(command, position[1:], velocity[1:], int(round(spacing_s * 1e6)))
        self.sequence += 1
        return self.link.write(rb.encode_plan(plan))

    def configure(self, limits: Limits) -> bool:
        """Install ``limits`` (and the 10 ms watchdog) on the board."""
        self.config_sequence += 1
        return self.link.write(rb.encode_config(limits.to_config(self.config_sequence)))

    async def run(self) -> None:
        await self.link.run()

    def close(self) -> None:
        self.link.close()
