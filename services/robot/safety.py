"""Limits the robot service enforces whatever arrives, and the command watchdog (pure)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

WATCHDOG_TIMEOUT_S = 0.010
CLAMP_TOLERANCE = 1e-4  # m or rad: smaller corrections are rounding, not limit events


@dataclass
class Limits:
    lower: np.ndarray
    upper: np.ndarray
    velocity: np.ndarray
    effort: np.ndarray

    @classmethod
    def from_model(cls, model) -> Limits:
        return cls(model.lower.copy(), model.upper.copy(), model.max_velocity.copy(), model.max_effort.copy())


class CommandRejectedError(ValueError):
    """A command that must not reach the motors; the message says why."""


def check_finite(values: np.ndarray, what: str) -> None:
    bad = ~np.isfinite(np.asarray(values, float))
    if bad.any():
        raise CommandRejectedError(f"{what} has non-finite values at joints {np.flatnonzero(bad).tolist()}")


def limit_step(target: np.ndarray, previous: np.ndarray, limits: Limits, dt: float) -> tuple[np.ndarray, list[str]]:
    """Clamp a position target into the joint range and the velocity limit from the previous target."""
    reasons = []
    clamped = np.clip(target, limits.lower, limits.upper)
    if np.any(np.abs(clamped - target) > CLAMP_TOLERANCE):
        reasons.append("position_limit")
    step = np.clip(clamped - previous, -limits.velocity * dt, limits.velocity * dt)
    if np.any(np.abs(previous + step - clamped) > CLAMP_TOLERANCE):
        reasons.append("velocity_limit")
    return previous + step, reasons


def clamp_effort(effort: np.ndarray, limits: Limits) -> np.ndarray:
    return np.clip(effort, -limits.effort, limits.effort)


class Watchdog:
    def __init__(self, timeout_s: float = WATCHDOG_TIMEOUT_S) -> None:
        self.timeout_s = timeout_s
        self.last_kick: float | None = None

    def kick(self, t: float) -> None:
        self.last_kick = t

    def expired(self, t: float) -> bool:
        return self.last_kick is None or t - self.last_kick > self.timeout_s
