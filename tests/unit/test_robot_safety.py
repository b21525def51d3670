"""Robot safety logic: limits, trajectory validation, and the board's 10 ms watchdog."""

from __future__ import annotations

import numpy as np

from services.robot.board_sim import BoardSim
from services.robot.safety import Limits, Watchdog, limit_step
from services.robot.tracking import TrajectoryFollower
from shared import msgs
from shared.kinematics import load_robot
from shared.protocols.robot_board import CommandFrame, Mode


def test_watchdog_brakes_within_10ms_of_the_last_command_100_of_100():
    rng = np.random.default_rng(0)
    names = load_robot("workcell").joint_names
    n = len(names)
    dt = 0.001
    for trial in range(100):
        board = BoardSim(names, feedback_period_s=dt)
        last_command = rng.uniform(0.05, 0.2)
        t, braked_at = 0.0, None
        while t < last_command + 0.05:
            if t <= last_command and round(t / dt) % 4 == 0:  # 250 Hz command stream, then silence
                board.receive(CommandFrame(trial, np.full(n, Mode.POSITION, np.uint8), np.zeros(n), np.zeros(n),
                                           np.zeros(n), np.zeros(n), np.zeros(n)), t)
                sent = t
            _, fb = board.step(t, np.zeros(n), np.full(n, 0.01), dt)
            if fb is not None and fb.watchdog_expired and braked_at is None and t > 0.01:
                braked_at = t
            t = round(t + dt, 9)
        assert braked_at is not None
        assert 0.010 < braked_at - sent <= 0.010 + dt + 1e-9, f"trial {trial}: braked {braked_at - sent:.4f} s"


def test_brake_only_damps_so_the_z_axes_sink_slowly():
    names = load_robot("workcell").joint_names
    board = BoardSim(names)
    effort, _ = board.step(1.0, np.zeros(len(names)), np.full(len(names), 0.01))
    z = names.index("left_z")
    assert effort[z] < 0 and abs(effort[z]) < 13.0  # less than the arm's weight: it descends, slowly


def test_limits_clamp_positions_and_velocities():
    model = load_robot("workcell")
    limits = Limits.from_model(model)
    prev = np.zeros(len(model.joint_names))
    target = np.full(len(prev), 10.0)
    out, reasons = limit_step(target, prev, limits, 0.004)
    assert set(reasons) == {"position_limit", "velocity_limit"}
    assert np.all(np.abs(out - prev) <= limits.velocity * 0.004 + 1e-12)
    assert Watchdog(0.01).expired(0.0)


def _trajectory(names, values, start=10.0):
    pts = [msgs.make("trajectory_msgs/msg/JointTrajectoryPoint", positions=np.asarray(v, float),
                     velocities=np.zeros(0), accelerations=np.zeros(0), effort=np.zeros(0),
                     time_from_start=msgs.make("builtin_interfaces/msg/Duration", sec=0, nanosec=int(k * 1e8)))
           for k, v in enumerate(values)]
    return msgs.make("trajectory_msgs/msg/JointTrajectory", header=msgs.header(start), joint_names=names, points=pts)


def test_follower_interpolates_reorders_and_rejects_bad_trajectories():
    names = ["a", "b"]
    f = TrajectoryFollower(names)
    assert f.load(_trajectory(["b", "a"], [[0.0, 1.0], [2.0, 3.0]]), 10.0) is None
    pos, vel = f.sample(10.05)
    np.testing.assert_allclose(pos, [2.0, 1.0])  # reordered to ("a", "b") and halfway
    np.testing.assert_allclose(vel, [20.0, 20.0])
    assert "NaN" in f.load(_trajectory(names, [[0.0, np.nan]]), 10.0)
    assert "lacks joints" in f.load(_trajectory(["a"], [[0.0]]), 10.0)
    assert f.load(_trajectory(names, []), 10.0) == "empty trajectory"
    np.testing.assert_allclose(f.sample(10.05)[0], [2.0, 1.0])  # the rejected ones changed nothing
