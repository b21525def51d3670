"""Limits the robot enforces whatever arrives, and the 10 ms command watchdog (pure, no I/O).

The same rules run on the host (services/robot) before a command is sent and on the control board
(the simulated one: services/robot/board_sim.py) before it reaches the motors, so a bad command is
stopped twice and both places count why. Reasons are ``"<kind>:<joint>"`` strings, kinds:
``non_finite``, ``unknown_mode``, ``position_limit``, ``velocity_limit``, ``effort_limit``,
``impedance_gain``, ``sensor_fault``, ``no_pneumatic_drive`` (PNEUMATIC mode asked of a joint
without a muscle pair: that joint brakes, like an unknown mode).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Protocol

import numpy as np

from services.robot.pneumatic import has_pneumatic_drive
from shared.protocols.robot_board import (
    JOINT_BRAKING,
    JOINT_EFFORT_LIMIT,
    JOINT_NON_FINITE,
    JOINT_POSITION_LIMIT,
    JOINT_VELOCITY_LIMIT,
    CommandFrame,
    ConfigFrame,
    Mode,
)

WATCHDOG_TIMEOUT_S = 0.010  # thesis 6.3
CLAMP_TOLERANCE = 1e-4  # m or rad: smaller corrections are float32 rounding, not limit events
# Soft limits: the host commands no closer to a URDF limit than this, so that tracking overshoot and
# the board's brake zone (services/robot/board_sim.py) never reach the hard stop. Trajopt plans with a
# wider margin (services/trajopt/optimizer.py), so a plan never meets the host's clamp.
SOFT_MARGIN_M = 0.0006
SOFT_MARGIN_RAD = 0.003
# Plain ints: comparing arrays with IntEnum members is slow, and this runs every control tick.
_BRAKE, _POSITION, _VELOCITY, _EFFORT, _IMPEDANCE, _PNEUMATIC = (int(m) for m in Mode)


@lru_cache(maxsize=16)
def pneumatic_joints(names: tuple[str, ...]) -> np.ndarray:
    """(n,) bool: which of these joints have a muscle pair (may run the PNEUMATIC mode)."""
    mask = np.array([has_pneumatic_drive(n) for n in names], bool)
    mask.flags.writeable = False
    return mask


class LimitsError(ValueError):
    """A limits table that cannot be used (missing joint or key, lower > upper, negative maximum)."""


class CommandRejectedError(ValueError):
    """A command that must not reach the motors at all; the message says why."""


@dataclass
class Limits:
    lower: np.ndarray  # (n,) position minimum, m or rad
    upper: np.ndarray  # (n,) position maximum
    velocity: np.ndarray  # (n,) |velocity| maximum
    effort: np.ndarray  # (n,) |effort| maximum, N or N m
    names: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        self.lower, self.upper, self.velocity, self.effort = (
            np.asarray(a, float).copy() for a in (self.lower, self.upper, self.velocity, self.effort))
        self.names = tuple(self.names) or tuple(f"joint{i}" for i in range(len(self.lower)))
        self.validate()

    def validate(self) -> None:
        n = len(self.names)
        for what in ("lower", "upper", "velocity", "effort"):
            a = getattr(self, what)
            if a.shape != (n,):
                raise LimitsError(f"limits: {what} has shape {a.shape}, expected ({n},)")
            if not np.isfinite(a).all():
                raise LimitsError(f"limits: {what} is not finite for {self._at(~np.isfinite(a))}")
        if (self.lower > self.upper).any():
            raise LimitsError(f"limits: lower > upper for {self._at(self.lower > self.upper)}")
        for what in ("velocity", "effort"):
            if (getattr(self, what) < 0).any():
                raise LimitsError(f"limits: negative {what} maximum for {self._at(getattr(self, what) < 0)}")

    def _at(self, mask: np.ndarray) -> list[str]:
        return [self.names[i] for i in np.flatnonzero(mask)]

    @classmethod
    def from_model(cls, model) -> Limits:
        """From a shared.kinematics RobotModel (URDF limits)."""
        return cls(model.lower, model.upper, model.max_velocity, model.max_effort, tuple(model.joint_names))

    def shrunk(self, margin: np.ndarray) -> Limits:
        """These limits with each position range narrowed by ``margin`` at both ends (a range narrower
        than twice its margin shrinks to its middle)."""
        margin = np.broadcast_to(np.asarray(margin, float), self.lower.shape)
        mid = (self.lower + self.upper) / 2
        lower = np.minimum(self.lower + margin, mid)
        upper = np.maximum(self.upper - margin, mid)
        return Limits(lower, upper, self.velocity, self.effort, self.names)

    @classmethod
    def from_dict(cls, table: dict, joint_names: list[str] | None = None) -> Limits:
        """``{joint: {"lower"|"min", "upper"|"max", "velocity", "effort"}}`` (optionally under "joints"),
        e.g. a deployment file's [robot.limits] table; ``joint_names`` fixes the order (all required)."""
        joints = table.get("joints", table)
        names = list(joint_names) if joint_names is not None else list(joints)
        missing = [n for n in names if n not in joints]
        if missing:
            raise LimitsError(f"limits: no entry for joints {missing}")
        rows = []
        for n in names:
            e = joints[n]
            try:
                rows.append([float(e["lower"] if "lower" in e else e["min"]),
                             float(e["upper"] if "upper" in e else e["max"]),
                             float(e["velocity"]), float(e["effort"])])
            except (KeyError, TypeError, ValueError) as exc:
                raise LimitsError(f"limits: joint {n}: needs lower/min, upper/max, velocity, effort "
                                  f"({exc!r})") from exc
        a = np.array(rows, float).reshape(len(names), 4)
        return cls(a[:, 0], a[:, 1], a[:, 2], a[:, 3], tuple(names))

    def to_dict(self) -> dict:
        return {n: {"lower": float(self.lower[i]), "upper": float(self.upper[i]),
                    "velocity": float(self.velocity[i]), "effort": float(self.effort[i])}
                for i, n in enumerate(self.names)}

    def to_config(self, sequence: int, watchdog_timeout_s: float = WATCHDOG_TIMEOUT_S) -> ConfigFrame:
        """The config/heartbeat frame that installs these limits on the board."""
        return ConfigFrame(int(round(watchdog_timeout_s * 1e6)), self.lower, self.upper, self.velocity,
                           self.effort, sequence=sequence)

    @classmethod
    def from_config(cls, cfg: ConfigFrame, names: list[str]) -> Limits:
        if not cfg.has_limits:
            raise LimitsError("config frame carries no limits")
        return cls(cfg.lower, cfg.upper, cfg.velocity, cfg.effort, tuple(names))


def soft_margins(model) -> np.ndarray:
    """(n,) the soft-limit margin of each joint of a RobotModel: SOFT_MARGIN_M for prismatic joints,
    SOFT_MARGIN_RAD for rotary ones."""
    kinds = {j.name: j.kind for j in model.joints}
    return np.array([SOFT_MARGIN_M if kinds.get(n) == "prismatic" else SOFT_MARGIN_RAD for n in model.joint_names])


def soft_limits(model) -> Limits:
    """The limits the host commands within: the URDF limits less ``soft_margins``."""
    return Limits.from_model(model).shrunk(soft_margins(model))


def board_limits(model) -> Limits:
    """The limits installed on the control board: the URDF limits less half of ``soft_margins``, so a
    setpoint at a soft limit is never clamped there and the board's brake zone stops a joint before
    the hard stop."""
    return Limits.from_model(model).shrunk(soft_margins(model) / 2)


class JointStateLike(Protocol):
    position: np.ndarray
    velocity: np.ndarray


@dataclass
class SafetyState:
    """What enforce() needs to know: the measured state and the last safe position setpoint."""

    position: np.ndarray
    velocity: np.ndarray
    last_safe: np.ndarray | None = None  # None: start from the measured position


def enforce(command: CommandFrame, state: JointStateLike, limits: Limits,
            dt: float) -> tuple[CommandFrame, list[str]]:
    """A command made safe, and why it changed (one ``"<kind>:<joint>"`` per event).

    Positions are clamped into the joint range and rate-limited to the velocity limit from the last
    safe setpoint (``state.last_safe`` if given, else the measured position); velocities and efforts
    are clamped; a velocity or effort command pushing further past a position limit is zeroed; a joint
    with any non-finite value holds its last safe position (zero feed-forward); a PNEUMATIC joint's
    target is clamped like a position setpoint, and a joint without a muscle pair asked for PNEUMATIC
    brakes (reason ``no_pneumatic_drive``). Raises
    CommandRejectedError if the joint count is wrong (nothing of such a frame can be trusted).
    """
    safe, reasons, _ = enforce_with_flags(command, state, limits, dt)
    return safe, reasons


def enforce_with_flags(command: CommandFrame, state: JointStateLike, limits: Limits,
                       dt: float) -> tuple[CommandFrame, list[str], np.ndarray]:
    """enforce(), plus the per-joint JOINT_* flags the board reports in its feedback."""
    n = len(limits.names)
    if command.n != n:
        raise CommandRejectedError(f"command has {command.n} joints, the robot has {n}")
    q = np.asarray(state.position, float)
    last = getattr(state, "last_safe", None)
    ref = q.copy() if last is None else np.asarray(last, float).copy()
    ref[~np.isfinite(ref)] = q[~np.isfinite(ref)]
    out = command.copy()
    flags = np.zeros(n, np.uint8)
    reasons: list[str] = []

    def flag(kind: str, mask: np.ndarray, bit: int) -> None:
        for i in np.flatnonzero(mask):
            if not flags[i] & bit or kind == "non_finite":
                reasons.append(f"{kind}:{limits.names[i]}")
            flags[i] |= bit

    mode = out.mode.astype(int)
    unknown = mode > _PNEUMATIC
    if unknown.any():
        reasons += [f"unknown_mode:{limits.names[i]}" for i in np.flatnonzero(unknown)]
        out.mode[unknown] = _BRAKE
    no_drive = (mode == _PNEUMATIC) & ~pneumatic_joints(limits.names)
    if no_drive.any():
        reasons += [f"no_pneumatic_drive:{limits.names[i]}" for i in np.flatnonzero(no_drive)]
        out.mode[no_drive] = _BRAKE
        unknown = unknown | no_drive
    fields = np.stack([out.position, out.velocity, out.effort, out.stiffness, out.damping])
    non_finite = ~np.isfinite(fields).all(axis=0) & ~unknown
    flag("non_finite", non_finite, JOINT_NON_FINITE)
    if non_finite.any():
        out.mode[non_finite] = _POSITION
        out.position[non_finite] = ref[non_finite]
        for f in ("velocity", "effort", "stiffness", "damping"):
            getattr(out, f)[non_finite] = 0.0
    blind = ~np.isfinite(ref)  # no measurement and no previous setpoint: nothing to hold, so brake
    if blind.any():
        reasons += [f"sensor_fault:{limits.names[i]}" for i in np.flatnonzero(blind)]
        out.mode[blind] = _BRAKE
    mode = out.mode.astype(int)
    braking = mode == _BRAKE
    flags[braking] |= JOINT_BRAKING
    for f in ("position", "velocity", "effort", "stiffness", "damping"):
        getattr(out, f)[braking] = 0.0

    uses_position = (mode == _POSITION) | (mode == _IMPEDANCE) | (mode == _PNEUMATIC)
    p = np.where(uses_position, out.position, ref)
    clamped = np.clip(p, limits.lower, limits.upper)
    flag("position_limit", uses_position & (np.abs(clamped - p) > CLAMP_TOLERANCE), JOINT_POSITION_LIMIT)
    step = np.clip(clamped - ref, -limits.velocity * dt, limits.velocity * dt)
    too_fast = uses_position & (np.abs(ref + step - clamped) > CLAMP_TOLERANCE)
    flag("velocity_limit", too_fast, JOINT_VELOCITY_LIMIT)
    out.position = np.where(uses_position, ref + step, out.position)

    v = np.clip(out.velocity, -limits.velocity, limits.velocity)
    flag("velocity_limit", np.abs(v - out.velocity) > 1e-9, JOINT_VELOCITY_LIMIT)
    e = np.clip(out.effort, -limits.effort, limits.effort)
    flag("effort_limit", np.abs(e - out.effort) > 1e-9, JOINT_EFFORT_LIMIT)
    # Driving further out of range in velocity or effort mode: stop that push, allow the way back.
    above, below = q >= limits.upper, q <= limits.lower
    outward_v = (mode == _VELOCITY) & ((above & (v > 0)) | (below & (v < 0)))
    outward_e = (mode == _EFFORT) & ((above & (e > 0)) | (below & (e < 0)))
    flag("position_limit", outward_v | outward_e, JOINT_POSITION_LIMIT)
    out.velocity = np.where(outward_v, 0.0, v)
    out.effort = np.where(outward_e, 0.0, e)
    negative = (mode == _IMPEDANCE) & ((out.stiffness < 0) | (out.damping < 0))
    if negative.any():
        reasons += [f"impedance_gain:{limits.names[i]}" for i in np.flatnonzero(negative)]
    out.stiffness = np.maximum(out.stiffness, 0.0)
    out.damping = np.maximum(out.damping, 0.0)
    return out, reasons, flags


def check_finite(values: np.ndarray, what: str) -> None:
    bad = ~np.isfinite(np.asarray(values, float))
    if bad.any():
        raise CommandRejectedError(f"{what} has non-finite values at joints {np.flatnonzero(bad).tolist()}")


def limit_step(target: np.ndarray, previous: np.ndarray, limits: Limits,
               dt: float) -> tuple[np.ndarray, list[str]]:
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
    """Command watchdog: expired when more than ``timeout_s`` passed since the last kick (or none yet).

    Times are compared in integer nanoseconds so that exactly 10 ms is never "expired" by float rounding.
    States: "waiting" (never kicked), "ok", "expired"; ``trips`` counts ok -> expired transitions.
    """

    def __init__(self, timeout_s: float = WATCHDOG_TIMEOUT_S) -> None:
        self.timeout_s = timeout_s
        self.last_kick: float | None = None
        self.trips = 0
        self.state = "waiting"

    @staticmethod
    def _ns(t: float) -> int:
        return int(round(t * 1e9))

    def kick(self, t: float) -> None:
        self.last_kick = t
        self.state = "ok"

    def check(self, t: float) -> bool:
        """True when expired (the motors must brake); updates ``state`` and ``trips``."""
        if self.last_kick is None:
            return True
        expired = self._ns(t) - self._ns(self.last_kick) > self._ns(self.timeout_s)
        if expired and self.state == "ok":
            self.trips += 1
        self.state = "expired" if expired else "ok"
        return expired

    def expired(self, t: float) -> bool:
        """Read-only form of check() (no state change)."""
        if self.last_kick is None:
            return True
        return self._ns(t) - self._ns(self.last_kick) > self._ns(self.timeout_s)

    def remaining(self, t: float) -> float:
        """Seconds until expiry (negative once expired, -inf before the first kick)."""
        if self.last_kick is None:
            return float("-inf")
        return self.last_kick + self.timeout_s - t
