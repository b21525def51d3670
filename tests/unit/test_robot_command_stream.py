"""The robot's command stream on a simulated clock: smooth trajectory time from a staircase clock,
no velocity clamps for a trajectory within the limit, and commands that reach the simulated board
at their arrival time so the watchdog sees the host's real gaps."""

from __future__ import annotations

import time

import numpy as np

from services.robot.safety import limit_step, soft_limits
from services.robot.service import VELOCITY_SLACK
from services.robot.tracking import CommandClock, TrajectoryFollower
from services.world.devices import BoardDevice
from shared import msgs
from shared.kinematics import load_robot
from shared.protocols import robot_board as rb

CLOCK_PERIOD = 0.01  # xm/clock at 100 Hz
COMMAND_PERIOD = 0.004  # commands at 250 Hz
TICK = 0.006  # the world's burst of physics steps


def staircase(t: float, lag: float = 0.002) -> float:
    """The deployment clock a service sees at true time ``t``: the last 100 Hz tick, ``lag`` late."""
    return np.floor(max(t - lag, 0.0) / CLOCK_PERIOD) * CLOCK_PERIOD


def command_times(seconds: float, seed: int = 0) -> np.ndarray:
    """Wall times of a command stream with up to 1 ms of wake-up jitter."""
    rng = np.random.default_rng(seed)
    return np.arange(0.0, seconds, COMMAND_PERIOD) + rng.uniform(0, 0.001, int(np.ceil(seconds / COMMAND_PERIOD)))


def test_command_clock_is_smooth_tracks_the_clock_and_stops_with_it():
    clock = CommandClock()
    times = command_times(5.0)
    out, steps, elapsed = [], [], np.diff(times, prepend=times[0] - COMMAND_PERIOD)
    for t, e in zip(times, elapsed, strict=True):
        value, step = clock.advance(staircase(t), e)
        out.append(value)
        steps.append(step / e)
    out, steps = np.array(out), np.array(steps[250:])  # after 1 s of settling
    assert np.all(np.diff(out) >= 0), "never backward"
    assert np.all(np.abs(out[250:] - times[250:]) < 0.012), "follows the clock"
    assert steps.min() > 0.9 and steps.max() <= 1.1 + 1e-9, "advances at wall rate (the staircase: 0 and 2.5)"
    # the clock stalls (world paused): trajectory time stops within max_lead_s of it
    frozen = staircase(times[-1])
    for _ in range(100):
        value, _ = clock.advance(frozen, COMMAND_PERIOD)
    assert frozen <= value <= frozen + clock.max_lead_s
    # the clock jumps back (world restart): it follows at once
    assert clock.advance(0.0, COMMAND_PERIOD) == (0.0, 0.0) and clock.jumps == 1


def trajectory(names: list[str], start: np.ndarray, velocity: np.ndarray, seconds: float):
    points = [msgs.make("trajectory_msgs/msg/JointTrajectoryPoint", positions=start + velocity * k * 0.05,
                        velocities=velocity, accelerations=np.zeros(0), effort=np.zeros(0),
                        time_from_start=msgs.make("builtin_interfaces/msg/Duration", sec=int(k * 0.05),
                                                  nanosec=int(round((k * 0.05 % 1) * 1e9))))
              for k in range(int(seconds / 0.05) + 1)]
    return msgs.make("trajectory_msgs/msg/JointTrajectory", header=msgs.header(0.0), joint_names=names,
                     points=points)


def clamps_following(use_command_clock: bool) -> int:
    """Velocity clamps of the host's rate limit following a trajectory at 95 % of the velocity limit."""
    model = load_robot("workcell")
    limits = soft_limits(model)
    start = (limits.lower + limits.upper) / 2
    follower = TrajectoryFollower(model.joint_names)
    velocity = np.where(np.arange(len(start)) % 2 == 0, 0.95, -0.95) * limits.velocity
    velocity[limits.velocity > 1] = 0.0  # rotary joints: stay in range
    assert follower.load(trajectory(model.joint_names, start, velocity, 0.4), 0.0) is None
    clock, target, clamps = CommandClock(max_rate=VELOCITY_SLACK), start.copy(), 0
    times = command_times(0.5, seed=1)
    for t, e in zip(times, np.diff(times, prepend=-COMMAND_PERIOD), strict=True):
        if use_command_clock:  # as RobotService._command_tick
            t_traj, advanced = clock.advance(staircase(t), e)
            dt = max(advanced, e)
        else:  # sampling at the deployment clock itself, rate-limited on wall time
            t_traj, dt = staircase(t), e
        goal, _ = follower.sample(t_traj)
        target, reasons = limit_step(goal, target, limits, dt)
        clamps += "velocity_limit" in reasons
    return clamps


def test_a_trajectory_within_the_velocity_limit_is_never_clamped():
    assert clamps_following(use_command_clock=False) > 10  # the staircase clock: the cause
    assert clamps_following(use_command_clock=True) == 0


def test_a_replan_while_trajectory_time_waits_for_a_late_clock_is_not_clamped():
    """The world runs late: its clock stands still, trajectory time stops within max_lead_s of it, and
    the planner's next trajectory differs from the last by a fraction of a millimetre at that time
    (another knot grid). Moving there within what the axes can do in the wall time is no clamp;
    a re-plan that jumps further than that still is."""
    model = load_robot("workcell")
    limits = soft_limits(model)
    start = (limits.lower + limits.upper) / 2
    follower = TrajectoryFollower(model.joint_names)
    assert follower.load(trajectory(model.joint_names, start, np.zeros(len(start)), 1.0), 0.0) is None
    clock, target = CommandClock(max_rate=VELOCITY_SLACK), start.copy()
    counts = []
    for offset in (0.3, 3.0):  # of what the axes may move in one command period
        replan = trajectory(model.joint_names, target + offset * limits.velocity * COMMAND_PERIOD,
                            np.zeros(len(start)), 1.0)
        clamps = 0
        for k in range(50):  # the clock stands at 0.1 s
            t_traj, advanced = clock.advance(0.1, COMMAND_PERIOD)
            if k == 40:
                assert advanced == 0.0 and t_traj == 0.1 + clock.max_lead_s, "trajectory time waits for the clock"
                assert follower.load(replan, 0.1) is None
            goal, _ = follower.sample(t_traj)
            target, reasons = limit_step(goal, target, limits, max(advanced, COMMAND_PERIOD))
            clamps += "velocity_limit" in reasons
        counts.append(clamps)
    assert counts[0] == 0 and counts[1] > 0


def test_after_the_clock_was_held_up_trajectory_time_catches_up_at_most_10_percent_fast():
    clock = CommandClock(max_rate=1.1)
    for k in range(250):
        clock.advance(staircase(k * COMMAND_PERIOD), COMMAND_PERIOD)
    t0 = k * COMMAND_PERIOD
    stalled = staircase(t0)
    rates = []
    for k in range(1, 200):  # no clock message for 100 ms, then they come again
        now = t0 + k * COMMAND_PERIOD
        t, step = clock.advance(stalled if k < 25 else staircase(now), COMMAND_PERIOD)
        rates.append(step / COMMAND_PERIOD)
    assert min(rates) >= 0 and max(rates) <= 1.1 + 1e-9, "slows down, then catches up no faster than 1.1x"
    assert min(rates[:5]) > 0.75, "no sudden stop when a clock message is late"
    assert abs(t - now) < 0.012, "back on the clock"


class StalledSim:
    """Enough of WorldSim for BoardDevice.step: the workcell at rest, time advanced by the caller."""

    def __init__(self, n: int) -> None:
        self.time, self.physics_dt, self.n = 0.0, 0.002, n

    def joint_state(self) -> tuple[np.ndarray, np.ndarray]:
        return np.full(self.n, 0.01), np.zeros(self.n)

    def set_efforts(self, efforts: np.ndarray) -> None:
        pass


def test_commands_reach_the_simulated_board_at_their_arrival_time(tmp_path):
    """The host commands every 4 ms (wall time) while the world stalls for 100 ms at a time and then
    catches up flat out. Handed over at their arrival times the commands keep the watchdog fed;
    handed over all at the first step after a stall (as the pty delivers them) the watchdog brakes."""
    names = load_robot("workcell").joint_names
    n = len(names)
    results = {}
    base = time.monotonic() + 1000.0  # past every horizon of the device's own stamper (no host writes to it)
    for mapped in (True, False):
        device = BoardDevice(str(tmp_path / f"board-{mapped}"), names)
        sim = StalledSim(n)
        command = rb.CommandFrame(0, np.full(n, rb.Mode.POSITION, np.uint8), *np.full((5, n), 0.0))
        try:
            for seq in range(300):  # 1.2 s of commands
                wall = base + seq * COMMAND_PERIOD
                command.sequence = seq
                device.arrived(rb.encode_command(command), wall)
                device.heard_until(wall)  # the stamper's next probe
                if seq % 25 == 24:  # the world wakes up and catches up to the wall time, a tick ahead
                    while sim.time < wall - base + TICK:
                        device.step(sim, (lambda w: w - base + TICK) if mapped else None, now=wall)
                        sim.time += sim.physics_dt
            results[mapped] = device.board.counters["brake_events"]
        finally:
            device.close()
    assert results[False] > 0, "without the arrival times the catch-up starves the watchdog"
    assert results[True] == 0


def test_before_a_new_trajectory_starts_the_one_it_replaced_still_holds():
    names = load_robot("workcell").joint_names
    n = len(names)
    follower = TrajectoryFollower(names)
    old = trajectory(names, np.zeros(n), np.full(n, 0.1), 1.0)
    new = trajectory(names, np.full(n, 0.5), np.zeros(n), 1.0)
    new.header = msgs.header(0.5)
    newer = trajectory(names, np.full(n, 0.6), np.zeros(n), 1.0)
    newer.header = msgs.header(0.55)
    assert follower.load(old, 0.0) is None and follower.load(new, 0.45) is None and follower.load(newer, 0.5) is None
    # a command time behind both newer ones: the old one, not a newer one's first knot
    np.testing.assert_allclose(follower.sample(0.45)[0], 0.045)
    np.testing.assert_allclose(follower.sample(0.52)[0], 0.5)
    np.testing.assert_allclose(follower.sample(0.6)[0], 0.6)
