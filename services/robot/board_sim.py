"""SIMULATED control board (thesis 6.2): per-joint control modes, motor currents, watchdog (pure).

The world feeds it decoded command frames and the measured joint state every physics step; it
returns motor efforts for MuJoCo and, at the feedback rate, a feedback frame. When no command
arrived for the watchdog timeout, it brakes: strong damping on every axis, so the Z axes sink
slowly under gravity, as on the real robot (thesis 6.3).
"""

from __future__ import annotations

import numpy as np

from services.robot.safety import WATCHDOG_TIMEOUT_S, Watchdog
from shared.protocols.robot_board import WATCHDOG_EXPIRED, CommandFrame, ConfigFrame, FeedbackFrame, Mode


def encoder_lsb(name: str) -> float:
    """Resolution of the 15-bit absolute encoder on the motor shaft, at the joint (thesis 6.2):
    linear axes 40 mm of belt per motor turn (Z axes geared 2:1), wrist and gripper 5:1."""
    if name.endswith("_z"):
        return 0.020 / 2 ** 15
    if name.endswith(("_x", "_y")):
        return 0.040 / 2 ** 15
    if "finger" in name:
        return 0.020 / 2 ** 15
    return 2 * np.pi / 5 / 2 ** 15


def _gains(name: str) -> tuple[float, float, float, float, float, float]:
    """kp, kd, ki, integral clamp, brake damping, torque constant for an axis by its kind."""
    if "finger" in name:
        return 300.0, 6.0, 0.0, 0.0, 20.0, 0.5
    if name.endswith("wrist"):
        return 30.0, 1.0, 5.0, 0.5, 2.0, 0.08
    if name.endswith("_z"):
        return 3000.0, 200.0, 8000.0, 40.0, 600.0, 4.0  # brake: ~2 cm/s descent under ~13 N
    return 2000.0, 150.0, 1000.0, 20.0, 1500.0, 4.0


class BoardSim:
    def __init__(self, joint_names: list[str], feedback_period_s: float = 0.004, seed: int = 0) -> None:
        self.joint_names = list(joint_names)
        g = np.array([_gains(n) for n in self.joint_names])
        self.kp, self.kd, self.ki, self.i_clamp, self.brake_damping, self.kt = g.T
        self.effort_max = np.array([5.0 if n.endswith("wrist") else 40.0 if "finger" in n else 200.0
                                    for n in self.joint_names])
        self.watchdog = Watchdog(WATCHDOG_TIMEOUT_S)
        self.command: CommandFrame | None = None
        self.integral = np.zeros(len(self.joint_names))
        self.feedback_period_s = feedback_period_s
        self._next_feedback = 0.0
        self.sequence = 0
        self.rng = np.random.default_rng(seed)
        self.brake_events = 0
        self._braking = True
        self.last_command_t: float | None = None
        self.lsb = np.array([encoder_lsb(n) for n in self.joint_names])

    def measure(self, q: np.ndarray) -> np.ndarray:
        """What the encoders report: quantized, with one LSB of noise."""
        counts = np.round(q / self.lsb) + self.rng.integers(-1, 2, len(q))
        return counts * self.lsb

    def receive(self, msg, t: float) -> None:
        if isinstance(msg, CommandFrame):
            if len(msg.mode) != len(self.joint_names):
                return  # a board ignores frames for another robot; the host sees no feedback change
            self.command = msg
            self.watchdog.kick(t)
            self.last_command_t = t
        elif isinstance(msg, ConfigFrame):
            self.watchdog.timeout_s = msg.watchdog_timeout_us * 1e-6

    def step(self, t: float, q: np.ndarray, qd: np.ndarray,
             dt: float = 0.001) -> tuple[np.ndarray, FeedbackFrame | None]:
        q = self.measure(q)
        expired = self.watchdog.expired(t)
        if expired and not self._braking:
            self.brake_events += 1
            self._next_feedback = t  # report the brake at once, not at the next feedback period
        self._braking = expired
        effort = np.zeros(len(q))
        c = self.command
        if expired or c is None:
            effort = -self.brake_damping * qd
            self.integral[:] = 0.0
        else:
            mode = c.mode.astype(int)
            err = c.position - q
            self.integral = np.clip(self.integral + err * dt, -self.i_clamp / np.maximum(self.ki, 1e-9),
                                    self.i_clamp / np.maximum(self.ki, 1e-9))
            pid = self.kp * err + self.kd * (c.velocity - qd) + self.ki * self.integral + c.effort
            effort = np.select(
                [mode == Mode.POSITION, mode == Mode.VELOCITY, mode == Mode.EFFORT, mode == Mode.IMPEDANCE],
                [pid, self.kd * 5 * (c.velocity - qd) + c.effort, c.effort,
                 c.stiffness * err + c.damping * (c.velocity - qd) + c.effort],
                default=-self.brake_damping * qd)
        effort = np.clip(effort, -self.effort_max, self.effort_max)
        feedback = None
        if t >= self._next_feedback:
            self._next_feedback = t + self.feedback_period_s - 1e-9
            current = effort / self.kt + self.rng.normal(0.0, 0.01, len(q))
            last = int(round(self.last_command_t * 1e6)) if self.last_command_t is not None else 0
            feedback = FeedbackFrame(self.sequence, int(round(t * 1e6)), WATCHDOG_EXPIRED if expired else 0,
                                     q.copy(), qd.copy(), current, last)
            self.sequence += 1
        return effort, feedback
