"""Following a JointTrajectory in time (pure): validation, reordering, interpolation, and the
smooth trajectory time a command stream samples at."""

from __future__ import annotations

import numpy as np

from shared import msgs

HISTORY = 10  # replaced trajectories kept for a command time behind the newest one's start


class TrajectoryFollower:
    """Holds the active trajectory as arrays; ``sample(t)`` gives the position/velocity target."""

    def __init__(self, joint_names: list[str]) -> None:
        self.joint_names = list(joint_names)
        # (times, positions, the trajectories it replaced, newest first) as one tuple: the command
        # thread samples while the loop loads
        self._active: tuple[np.ndarray, np.ndarray, tuple] | None = None

    @property
    def times(self) -> np.ndarray | None:
        return None if self._active is None else self._active[0]

    @property
    def positions(self) -> np.ndarray | None:
        return None if self._active is None else self._active[1]

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
        previous = self._active
        history = ((previous[:2],) + previous[2])[:HISTORY] if previous is not None else ()
        self._active = (times, positions, history)
        return None

    def sample(self, t: float) -> tuple[np.ndarray, np.ndarray] | None:
        """Position and velocity at ``t``. Before the start of the newest trajectory the newest of
        those it replaced that has started holds (the planner stamps a trajectory with its own clock,
        which may run ahead of the command time: holding the new one's first point there would jump)."""
        active = self._active
        if active is None:
            return None
        times, pos, history = active
        if t < times[0]:
            older = next((h for h in history if h[0][0] <= t), None)
            if older is not None:
                times, pos = older
        if len(times) == 1 or t <= times[0]:
            return pos[0].copy(), np.zeros(pos.shape[1])
        if t >= times[-1]:
            return pos[-1].copy(), np.zeros(pos.shape[1])
        k = int(np.searchsorted(times, t) - 1)
        s = (t - times[k]) / (times[k + 1] - times[k])
        vel = (pos[k + 1] - pos[k]) / (times[k + 1] - times[k])
        return pos[k] + s * (pos[k + 1] - pos[k]), vel


class CommandClock:
    """Trajectory time for a command stream that runs on its own period.

    The deployment clock a service sees is a staircase in simulation (xm/clock arrives at 100 Hz,
    late by the transport) while commands go out at 250 Hz: sampling the trajectory at that clock
    moves the setpoint 10 ms at once and then not at all, which the velocity limit clamps although
    the trajectory itself is within it. This clock advances by the wall time elapsed between
    commands, pulled gently toward the deployment clock (``gain`` of the difference per command),
    never backward and never faster than ``max_rate`` times the wall time (catching up after the
    clock's messages were held up moves a plan at most that much faster than planned), at most
    ``max_lead_s`` ahead of it (a stalled clock stops it); a difference over ``jump_s`` (a world
    restart, a replay looping) snaps it to the clock.
    """

    def __init__(self, gain: float = 0.05, max_lead_s: float = 0.05, jump_s: float = 0.5,
                 max_rate: float = 1.1) -> None:
        self.gain = gain
        self.max_lead_s = max_lead_s
        self.jump_s = jump_s
        self.max_rate = max_rate
        self.t: float | None = None
        self.jumps = 0

    def advance(self, clock_now: float, elapsed_s: float) -> tuple[float, float]:
        """The new trajectory time and how far it advanced, ``elapsed_s`` wall seconds after the last call."""
        if self.t is None or abs(clock_now - self.t) > self.jump_s:
            self.jumps += self.t is not None
            self.t = clock_now
            return self.t, 0.0
        step = min(max(0.0, elapsed_s + self.gain * (clock_now - self.t)), self.max_rate * elapsed_s)
        step = max(0.0, min(step, clock_now + self.max_lead_s - self.t))
        self.t += step
        return self.t, step
