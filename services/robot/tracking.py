"""Following a JointTrajectory in time (pure): validation, reordering, interpolation."""

from __future__ import annotations

import numpy as np

from shared import msgs


class TrajectoryFollower:
    """Holds the active trajectory as arrays; ``sample(t)`` gives the position/velocity target."""

    def __init__(self, joint_names: list[str]) -> None:
        self.joint_names = list(joint_names)
        self.times: np.ndarray | None = None
        self.positions: np.ndarray | None = None

    def load(self, msg, now: float) -> str | None:
        """Adopt a trajectory message; returns a rejection reason or None."""
        if not msg.points:
            return "empty trajectory"
        index = {n: i for i, n in enumerate(msg.joint_names)}
        missing = [n for n in self.joint_names if n not in index]
        if missing:
            return f"trajectory lacks joints {missing}"
        order = [index[n] for n in self.joint_names]
        start = msgs.stamp_seconds(msg.header.stamp)
        times = np.array([start + p.time_from_start.sec + p.time_from_start.nanosec * 1e-9 for p in msg.points])
        try:
            positions = np.array([np.asarray(p.positions, float)[order] for p in msg.points])
        except IndexError:
            return "a trajectory point has fewer positions than joint names"
        if not np.isfinite(positions).all() or not np.isfinite(times).all():
            return "trajectory contains NaN or infinite values"
        if np.any(np.diff(times) <= 0):
            return "trajectory times are not increasing"
        self.times, self.positions = times, positions
        return None

    def sample(self, t: float) -> tuple[np.ndarray, np.ndarray] | None:
        if self.times is None:
            return None
        times, pos = self.times, self.positions
        if len(times) == 1 or t <= times[0]:
            return pos[0].copy(), np.zeros(pos.shape[1])
        if t >= times[-1]:
            return pos[-1].copy(), np.zeros(pos.shape[1])
        k = int(np.searchsorted(times, t) - 1)
        s = (t - times[k]) / (times[k + 1] - times[k])
        vel = (pos[k + 1] - pos[k]) / (times[k + 1] - times[k])
        return pos[k] + s * (pos[k + 1] - pos[k]), vel
