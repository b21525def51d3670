"""Building blocks of the scripted teacher: minimum-jerk tracks through waypoints and yaw rotations."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


def rot_z(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def yaw_quat(yaw: float) -> np.ndarray:
    return np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)])


def min_jerk(s: np.ndarray) -> np.ndarray:
    s = np.clip(s, 0.0, 1.0)
    return s ** 3 * (10 - 15 * s + 6 * s ** 2)


@dataclass
class Track:
    """Piecewise minimum-jerk trajectory through (time, value) waypoints."""

    times: list[float] = field(default_factory=list)
    values: list[np.ndarray] = field(default_factory=list)

    def add(self, t: float, value) -> Track:
        self.times.append(t)
        self.values.append(np.atleast_1d(np.asarray(value, float)))
        return self

    def hold(self, t: float) -> Track:
        return self.add(t, self.values[-1])

    def __call__(self, t: float) -> np.ndarray:
        times = self.times
        if t <= times[0]:
            return self.values[0]
        if t >= times[-1]:
            return self.values[-1]
        k = int(np.searchsorted(times, t, side="right")) - 1
        s = min_jerk(np.array((t - times[k]) / max(times[k + 1] - times[k], 1e-9)))
        return self.values[k] + (self.values[k + 1] - self.values[k]) * s
