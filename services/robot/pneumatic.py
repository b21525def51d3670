"""Two-stage control of a pneumatic-muscle hand joint (thesis 7.3.2) (pure).

Each joint is driven by an antagonistic pair of muscles. The lower stage regulates each muscle's
pressure to a setpoint through its valve (PI on the pressure error). The upper stage turns the
joint position error into a pressure differential through a proportional stiffness (plus a
narrowly clamped integral), added to and subtracted from a fixed bias. Against an obstacle the
differential, and so the contact force, settles at stiffness x error instead of growing: the
single-stage controller (position PID straight onto the valves) keeps filling the muscle.

The simulated control board (services/robot/board_sim.py) runs this controller for joints in the
PNEUMATIC mode (docs/protocols/robot_board.md): the pressures integrate with ``muscle_pressures``,
MuJoCo integrates the joint. ``pneumatic_params`` is the one table of per-joint drive parameters.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from shared.robots.registry import joints_with

P_MAX = 4.0  # bar
BIAS = 1.5  # bar


def muscle_pressures(p: np.ndarray, valves: np.ndarray, fill_rate, leak, dt: float) -> np.ndarray:
    """Muscle pressures (bar) after ``dt`` under valve commands in [-1, 1] (fill > 0, vent < 0): each
    valve fills at ``fill_rate`` bar/s per unit command, each muscle leaks ``leak`` x its pressure per
    second; pressures stay in [0, P_MAX]. Works on one pair (2,) or on a board's joints (2, n)."""
    return np.clip(p + (fill_rate * np.clip(valves, -1, 1) - leak * p) * dt, 0.0, P_MAX)


@dataclass
class MusclePair:
    """Plant: two muscles on one joint. Torque ~ pressure difference; valves fill and vent."""

    inertia: float = 2e-4
    damping: float = 0.01
    torque_per_bar: float = 0.05  # N m / bar
    fill_rate: float = 8.0  # bar/s per unit valve command
    leak: float = 0.05  # 1/s
    q: float = 0.0
    qd: float = 0.0
    p: np.ndarray = field(default_factory=lambda: np.array([BIAS, BIAS]))  # flexor, extensor
    wall: float | None = None  # joint angle of an obstacle (contact when q reaches it)

    def step(self, valves: np.ndarray, dt: float) -> float:
        """Advance with valve commands in [-1, 1] (fill > 0, vent < 0); returns contact torque."""
        self.p = muscle_pressures(self.p, valves, self.fill_rate, self.leak, dt)
        torque = self.torque_per_bar * (self.p[0] - self.p[1]) - self.damping * self.qd
        self.qd += torque / self.inertia * dt
        self.q += self.qd * dt
        contact = 0.0
        if self.wall is not None and self.q > self.wall:
            contact = torque
            self.q, self.qd = self.wall, 0.0
        return contact


@dataclass
class TwoStageController:
    """Gains and state are scalars for one joint or (n,) arrays (state: integral (n,), p_integral
    (2, n)) for a board's joints; pressures and valve commands are then (2, n)."""

    stiffness: float = 6.0  # bar per rad: the proportional stiffness of the upper stage
    ki: float = 2.0
    i_clamp: float = 0.2  # bar: the narrowly clamped integral term
    kd: float = 0.3
    kp_pressure: float = 4.0
    ki_pressure: float = 2.0
    integral: float = 0.0
    p_integral: np.ndarray = field(default_factory=lambda: np.zeros(2))

    def pressures(self, q_des: float, q: float, qd: float, dt: float) -> np.ndarray:
        err = q_des - q
        self.integral = np.clip(self.integral + self.ki * err * dt, -self.i_clamp, self.i_clamp)
        diff = self.stiffness * err + self.integral - self.kd * qd
        return np.clip(np.array([BIAS + diff / 2, BIAS - diff / 2]), 0.0, P_MAX)

    def valves(self, p_des: np.ndarray, p: np.ndarray, dt: float) -> np.ndarray:
        err = p_des - p
        self.p_integral = np.clip(self.p_integral + err * dt, -0.5, 0.5)
        return np.clip(self.kp_pressure * err + self.ki_pressure * self.p_integral, -1.0, 1.0)

    def command(self, q_des: float, plant: MusclePair, dt: float) -> np.ndarray:
        return self.valves(self.pressures(q_des, plant.q, plant.qd, dt), plant.p, dt)


@dataclass
class SingleStageController:
    """The original scheme: a position PID writes valve commands directly (for comparison)."""

    kp: float = 5.0
    ki: float = 5.0
    integral: float = 0.0

    def command(self, q_des: float, plant: MusclePair, dt: float) -> np.ndarray:
        err = q_des - plant.q
        self.integral += err * dt
        u = self.kp * err + self.ki * self.integral
        return np.clip(np.array([u, -u]), -1.0, 1.0)


# Joints with a muscle pair: those the robot descriptions list (the hand-arm's fingers, shared/robots).
PNEUMATIC_JOINTS = joints_with("pneumatic_joints")


@dataclass(frozen=True)
class PneumaticParams:
    """One joint's muscle pair and two-stage controller, as the board runs it (PNEUMATIC mode).

    Pressure dynamics and gains are MusclePair's and TwoStageController's except two, scaled to
    the hand-arm's finger joints in MuJoCo (services/world/model.py): each carries about 10x the
    plant's inertia (1e-3 kg m^2 of armature per joint, the distal joint coupled to the middle one:
    1.2e-3 to 2e-3 kg m^2 at the joint), so 0.5 N m/bar (10x) keeps the plant's stiffness/inertia
    ratio, and the full differential (P_MAX, 4 bar) gives 2 N m, the URDF effort limit of the finger
    joints. MuJoCo's finger damping (0.01 N m s/rad) is only 0.02 bar s/rad at that scale where the
    plant's own damping is 0.2, so kd rises from 0.3 to 0.6 bar s/rad: measured on index_j1/j2 and
    thumb_j0/j1 (0.4-0.8 rad steps), kd 0.3 ends in a limit cycle, 0.5 overshoots up to 0.1 rad,
    0.6 is within 0.05 rad after 0.25-0.3 s with at most 0.035 rad overshoot.
    """

    torque_per_bar: float = 0.5  # N m / bar
    fill_rate: float = 8.0  # bar/s per unit valve command
    leak: float = 0.05  # 1/s
    stiffness: float = 6.0  # bar/rad (upper stage)
    ki: float = 2.0  # bar/(rad s)
    i_clamp: float = 0.2  # bar
    kd: float = 0.6  # bar s/rad
    kp_pressure: float = 4.0  # valve command per bar (lower stage)
    ki_pressure: float = 2.0  # valve command per bar s


def has_pneumatic_drive(name: str) -> bool:
    return name in PNEUMATIC_JOINTS


def pneumatic_params(name: str) -> PneumaticParams | None:
    """The joint's pneumatic drive, or None where it has none (arm joints, the workcell gantry)."""
    return PneumaticParams() if has_pneumatic_drive(name) else None
