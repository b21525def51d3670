"""Two-stage control of a pneumatic-muscle hand joint (thesis 7.3.2) (pure).

Each joint is driven by an antagonistic pair of muscles. The lower stage regulates each muscle's
pressure to a setpoint through its valve (PI on the pressure error). The upper stage turns the
joint position error into a pressure differential through a proportional stiffness (plus a
narrowly clamped integral), added to and subtracted from a fixed bias. Against an obstacle the
differential, and so the contact force, settles at stiffness x error instead of growing: the
single-stage controller (position PID straight onto the valves) keeps filling the muscle.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

P_MAX = 4.0  # bar
BIAS = 1.5  # bar


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
        self.p = np.clip(self.p + (self.fill_rate * np.clip(valves, -1, 1) - self.leak * self.p) * dt, 0.0, P_MAX)
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
        self.integral = float(np.clip(self.integral + self.ki * err * dt, -self.i_clamp, self.i_clamp))
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
