"""Joint limits that hold: the host's soft limits, the board's limits and brake zone, and the
physics in between. Goals at and beyond every limit of the workcell, through the host's command
shaping, the simulated board and MuJoCo: the measured positions stay inside the URDF limits."""

from __future__ import annotations

import numpy as np
import pytest

from services.robot.board_sim import BoardSim, encoder_lsb
from services.robot.safety import Limits, board_limits, limit_step, soft_limits, soft_margins
from services.trajopt.optimizer import TrajoptConfig
from services.world.sim import WorldSim
from shared.kinematics import load_robot
from shared.protocols import robot_board as rb

COMMAND_PERIOD_S = 0.004


def test_limits_nest_inside_the_urdf_limits():
    model = load_robot("workcell")
    hard, board, soft = Limits.from_model(model), board_limits(model), soft_limits(model)
    assert np.all(hard.lower < board.lower) and np.all(board.lower < soft.lower)
    assert np.all(soft.upper < board.upper) and np.all(board.upper < hard.upper)
    cfg = TrajoptConfig()
    prismatic = np.array([j.kind == "prismatic" for j in model.moving])
    plan_margin = np.where(prismatic, cfg.limit_margin_m, cfg.limit_margin_rad)
    assert np.all(plan_margin > soft_margins(model)), "plans keep inside what the robot clamps to"


def drive(sim: WorldSim, board: BoardSim, goal: np.ndarray, seconds: float, host: Limits | None,
          feed_forward: bool) -> tuple[np.ndarray, np.ndarray]:
    """Command ``goal`` through the host's rate limit into ``host`` limits (None: raw, straight to the
    board) for ``seconds``; returns the measured positions (board feedback) and the true ones, per step."""
    n = len(sim.joint_names)
    q, _ = sim.joint_state()
    target = q.copy() if host is None else np.clip(q, host.lower, host.upper)
    raw = Limits(np.full(n, -1e9), np.full(n, 1e9), board.limits.velocity, board.limits.effort, board.limits.names)
    next_command, seq = 0.0, 0
    measured, true = [], []
    for _ in range(int(seconds / sim.physics_dt)):
        t = sim.time
        if t >= next_command:
            previous = target
            target, _ = limit_step(goal, target, host or raw, COMMAND_PERIOD_S)
            velocity = (target - previous) / COMMAND_PERIOD_S if feed_forward else np.zeros(n)
            board.receive(rb.CommandFrame(seq, np.full(n, rb.Mode.POSITION, np.uint8), target, velocity,
                                          np.zeros(n), np.zeros(n), np.zeros(n)), t)
            seq += 1
            next_command = t + COMMAND_PERIOD_S - 1e-9
        q, qd = sim.joint_state()
        effort, feedback = board.step(t, q, qd, sim.physics_dt)
        if feedback is not None:
            measured.append(feedback.position)
        sim.set_efforts(effort)
        sim.step(1)
        true.append(sim.joint_state()[0])
    return np.array(measured), np.array(true)


# The margins are sub-millimetre (the gripper must reach 2 mm above the table to grasp the 4 mm lens),
# so a joint driven at its velocity limit into a soft limit may overshoot it by a few hundredths of a mm.
OVERSHOOT = 1e-4


@pytest.fixture(scope="module")
def workcell():
    return WorldSim(robot="workcell")


@pytest.mark.parametrize("beyond", [0.0, 0.05])
def test_measured_positions_stay_inside_for_goals_at_and_beyond_every_limit(workcell, beyond):
    """Every joint of the workcell, to each end of its range and ``beyond`` past it (m or rad), at the
    velocity limit: the encoders never report a position more than 0.1 mm (or mrad) outside the URDF
    limits (beyond one LSB), and MuJoCo's joint never presses further into its hard stop (after the
    first 0.2 s, which leave the home pose on the lower stops of the Z axes and fingers)."""
    sim = workcell
    model = sim.robot
    hard, soft = Limits.from_model(model), soft_limits(model)
    lsb = np.array([encoder_lsb(n) for n in sim.joint_names])
    worst: dict[str, float] = {}
    for j, name in enumerate(sim.joint_names):
        if model.moving[j].mimic is not None:
            continue  # follows its master (checked with it)
        for end in ("lower", "upper"):
            sim.reset(0)
            sim.set_robot_mode("robot")
            board = BoardSim(sim.joint_names, board_limits(model))
            goal = np.clip(sim.joint_state()[0], soft.lower, soft.upper)
            goal[j] = hard.lower[j] - beyond if end == "lower" else hard.upper[j] + beyond
            measured, true = drive(sim, board, goal, 1.5, soft, feed_forward=True)
            # the home pose rests on the Z axes' and fingers' lower stops: judged once commanded inside
            measured, true = measured[50:], true[100:]
            over_measured = np.maximum(measured - hard.upper, hard.lower - measured) - lsb
            over_true = np.maximum(true - hard.upper, hard.lower - true)
            worst[f"{name} {end}"] = max(over_measured.max(), over_true.max())
    bad = {k: f"{v * 1e3:+.3f}" for k, v in worst.items() if v > OVERSHOOT}
    assert not bad, f"beyond the URDF limits (mm or mrad): {bad}"


def test_board_brakes_a_joint_before_its_hard_stop_whatever_the_host_sends(workcell):
    """A host that ignores the soft limits: raw goals 5 cm past every limit, no velocity feed-forward
    (so the position loop lags and winds up its integral). The board clamps the setpoints into its
    limits and brakes joints that would coast on: every joint stays within 0.35 mm of its range
    (the Z axes, loaded by the arm's weight, come closest) where without the brake zone they ran into
    the hard stop."""
    sim = workcell
    model = sim.robot
    hard = Limits.from_model(model)
    worst, brakes = 0.0, 0
    for j, name in enumerate(sim.joint_names):
        if model.moving[j].mimic is not None or not name.endswith(("_x", "_z")):
            continue
        sim.reset(0)
        sim.set_robot_mode("robot")
        board = BoardSim(sim.joint_names, board_limits(model))
        goal = sim.joint_state()[0]
        goal[j] = hard.upper[j] + 0.05
        _, true = drive(sim, board, goal, 1.0, None, feed_forward=False)
        worst = max(worst, (true[:, j] - hard.upper[j]).max())
        brakes += board.counters["limit_brakes"]
    assert brakes > 0
    assert worst < 0.00035, f"{worst * 1e3:.3f} mm past the hard stop"
