"""Robot in the loop (`xm eval --execute`): the learned policy drives the simulated workcell robot on
the validation layouts and the world judges the result.

One process, the same parts as the running cell without the transport: the world's MuJoCo model
in robot mode with the layout of a validation demonstration, the policy stepped at its sample
period (hands from its own prediction, objects observed from the world's truth: the interactive
neural simulation of 7.6.1), the trajectory optimizer of 7.4 replanning on every plan, and the
simulated control board (position mode, watchdog, limits) stepped with the physics. Success is
the world's assembly test (camera module seated on the board's connector, board lifted).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.policy.simulate import PolicyRunner, SceneObs
from services.robot.board_sim import BoardSim
from services.trajopt.mapping import PlanArrays, goals_for_horizon
from services.trajopt.optimizer import TrajectoryOptimizer, TrajoptConfig
from services.world.sim import WorldSim
from shared.demo import HAND_NAMES, KEYPOINTS_PER_HAND, TACTILE_REGIONS
from shared.kinematics import load_robot
from shared.protocols.robot_board import CommandFrame, Mode

HAND_POINTS = [f"{h}/{k}" for h in HAND_NAMES for k in range(KEYPOINTS_PER_HAND)]
GRIPPER_JOINTS = ("left_finger_a", "left_finger_b")
THUMB, INDEX = TACTILE_REGIONS.index("thumb"), TACTILE_REGIONS.index("index")
GRASP_KPA = 10.0  # the teacher's grasp reads 2 x 20 kPa on thumb and index; 10 kPa = a quarter of it
GRASP_EFFORT_N_PER_KPA = 0.1  # kPa over a ~1 cm^2 fingertip -> N


@dataclass
class ExecutionResult:
    seed: int
    demo: int
    grasp_hand: str
    success: bool
    seconds: float  # simulated
    tracking_mm: float  # median distance of the robot's mapped points to the policy's goals
    solves_rejected: int
    object_motion_mm: float  # how far the camera module moved from its start
    closest_mm: float  # closest approach of the gripper's finger-tip midpoint to the module's lens point
    opening_mm: float  # gripper finger opening (sum of both fingers) at that moment
    max_grasp_kpa: float  # largest predicted left thumb + index pressure (7.2.10), 0 without tactile

    def to_dict(self) -> dict:
        return dict(self.__dict__)


def execute_layout(model, seed: int, demo: int, seconds: float = 9.0, plan_period_s: float = 0.1,
                   knots: int = 20, horizon_s: float = 1.0, grasp_kpa: float | None = GRASP_KPA) -> ExecutionResult:
    """Runs one validation layout (``assembly_protocol(seed)[demo]``) with the robot in the loop.

    ``grasp_kpa``: above this predicted left thumb + index pressure the gripper is commanded shut
    with an effort proportional to it (None: fingers follow the mapped thumb and index tips only)."""
    sim = WorldSim("assembly", seed=seed, width=32, height=24)  # cameras unused here
    sim.start_demo(demo)
    start_hands = sim.hand_keypoints()  # the teacher's pose at the start: the policy's initial hands
    sim.set_robot_mode("robot")
    robot = load_robot("workcell")
    opt = TrajectoryOptimizer(robot, TrajoptConfig(knots=knots))
    board = BoardSim(sim.joint_names)
    runner = PolicyRunner(model)
    opt_dt = horizon_s / knots
    steps = int(round(seconds / model.dt))
    plan_every = max(1, int(round(plan_period_s / model.dt)))
    physics_per_step = max(1, int(round(model.dt / sim.physics_dt)))
    names, objects = sim.object_keypoints()
    cam = [i for i, n in enumerate(names) if n.startswith("camera/")]
    cam0 = objects[cam].mean(axis=0)
    hand_mask = np.ones((2, KEYPOINTS_PER_HAND), bool)
    obj_mask = np.ones(len(names), bool)
    hands = start_hands
    q, _ = sim.joint_state()
    current, t_current = np.repeat(q[None], knots, axis=0), 0.0
    n = len(sim.joint_names)
    success, rejected, tracking = False, 0, []
    fingers = [sim.joint_names.index(j) for j in GRIPPER_JOINTS]
    tips = [opt.point_names.index(p) for p in ("left/4", "left/8")]
    lens = names.index("camera/lens")
    closest, opening, max_kpa = np.inf, np.nan, 0.0
    for k in range(steps):
        t = sim.time
        _, objects = sim.object_keypoints()
        # the policy's own next hands (runner.state keeps the observation it was given)
        hands = runner.step(SceneObs(hands, hand_mask, objects, obj_mask))[:len(HAND_POINTS)].reshape(
            2, KEYPOINTS_PER_HAND, 3)
        if k % plan_every == 0:
            horizon = runner.horizon(None, int(round(horizon_s / model.dt)) + 1)
            plan = PlanArrays(t, model.dt, HAND_POINTS + list(names), horizon,
                              np.ones(horizon.shape[:2], bool))
            goals, mask = goals_for_horizon(plan, opt.point_names, t, opt_dt, knots)
            shift = max(0, min(knots - 1, round((t - t_current) / opt_dt)))
            if shift:
                current = np.concatenate([current[shift:], np.repeat(current[-1:], shift, 0)])
            t_current = t
            result = opt.solve(current, goals, mask, opt_dt)
            if result.ok:
                current = result.q
            else:
                rejected += 1
            q_now, _ = sim.joint_state()
            reached = opt.points(q_now)
            tracking.append(float(np.median(np.linalg.norm(reached - goals[0], axis=-1)[mask[0]]))
                            if mask[0].any() else np.nan)
        # the executing trajectory, sampled now: linear between knots
        s = np.clip((t - t_current) / opt_dt, 0, knots - 1)
        i = int(s)
        j = min(i + 1, knots - 1)
        q_cmd = current[i] + (s - i) * (current[j] - current[i])
        v_cmd = (current[j] - current[i]) / opt_dt
        effort = np.zeros(n)
        kpa = float(runner.efforts[0, THUMB] + runner.efforts[0, INDEX]) if runner.efforts.size else 0.0
        max_kpa = max(max_kpa, kpa)
        if grasp_kpa is not None and kpa > grasp_kpa:  # 7.2.10: predicted touch becomes squeeze
            q_cmd[fingers] = 0.0
            effort[fingers] = -GRASP_EFFORT_N_PER_KPA * kpa
        board.receive(CommandFrame(k, np.full(n, Mode.POSITION, np.uint8), q_cmd, v_cmd, effort, np.zeros(n),
                                   np.zeros(n)), sim.time)
        for _ in range(physics_per_step):
            q, qd = sim.joint_state()
            efforts, _ = board.step(sim.time, q, qd, sim.physics_dt)
            sim.set_efforts(efforts)
            sim.step(1)
        success = success or sim.assembly_success()
        if k % plan_every == 0:
            q_now, _ = sim.joint_state()
            _, objects = sim.object_keypoints()
            gap = float(np.linalg.norm(opt.points(q_now)[tips].mean(axis=0) - objects[lens]))
            if gap < closest:
                closest, opening = gap, float(q_now[fingers].sum())
    _, objects = sim.object_keypoints()
    return ExecutionResult(seed, demo, sim.teacher.grasp_hand, bool(success), sim.time,
                           float(np.nanmedian(tracking) * 1e3) if tracking else float("nan"), rejected,
                           float(np.linalg.norm(objects[cam].mean(axis=0) - cam0) * 1e3), closest * 1e3,
                           opening * 1e3, max_kpa)
