"""Robot in the loop for the carry tasks (pick_place, wiping): the learned policy drives the
simulated workcell robot on a validation layout and the world's physical success test judges it.

The same parts as the assembly's loop (evaluation/execute.py): the world's MuJoCo model in robot
mode, the policy stepped at its sample period (objects observed from the world's truth, the
grasping hand observed at the gripper once the gripper has caught up with it), the trajectory
optimizer replanning every 0.1 s, the simulated control board stepped with the physics.

Robot mapping (the registry's ``RobotMapping``, services/world/tasks.py): the hand that grasps in
the policy's own look-ahead drives the gripper (its thumb and index tips the pads), the other hand
parks (the finger goes home). Predicted touch becomes effort (7.2.10): thumb + index pressure
shuts the gripper; on wiping, the predicted middle + ring + palm pressure of the grasping hand
(the glove's press regions) is the gripper's downward force, force-controlled in z (no stiffness,
the carriage's weight held by what the position loop held) while the pad is over the plate and
within 5 mm of it. pick_place: the gripper's pads close ``GRASP_DEPTH_M`` below the hand's pinch
(the hand pinches the 5 cm box's top edges, the parallel gripper holds it by its sides).

Contact anchors (evaluation/carry.py), when given: the pinch is pulled onto the observed grasp
point and the gripper opens at least the demonstrated grasp width while reaching; the demonstrated
grip force; pick_place: the box set onto the plate where the demonstrations set it; wiping: the
pad lowered onto the marked area and pressed with the demonstrated force.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from evaluation.anchors import pinch
from evaluation.carry import (
    CONTACT_MARGIN_M,
    PRESS_REGIONS,
    CarryAnchors,
    CarryState,
    carry_horizon,
    over_area,
)
from evaluation.execute import (
    EFFORT_N_PER_KPA,
    FRAME_EVERY,
    GRASP_KPA,
    GRIP_SETTLE_S,
    HOLD_M,
    INDEX,
    LOOKAHEAD_S,
    LOST_M,
    ROBOT,
    ROLES,
    THUMB,
    TOUCH_RAMP_S,
    TeacherReplay,
    gripper_flipped,
    hand_point_names,
    observed_hands,
    physics_step,
    receding_solve,
    sample_trajectory,
    touch_switch,
)
from services.policy.runner import PolicyRunner, SceneObs
from services.robot.board_sim import BoardSim, axis_params
from services.trajopt.mapping import PlanArrays, goals_for_horizon
from services.trajopt.optimizer import TrajectoryOptimizer, TrajoptConfig
from services.world.sim import WorldSim
from services.world.teacher import KPA_PER_N
from shared.demo import FINGERTIPS, HAND_NAMES, KEYPOINTS_PER_HAND
from shared.kinematics import load_robot
from shared.protocols.robot_board import CommandFrame, Mode

CARRY_TASKS = ("pick_place", "wiping")
GRASP_POINT = {"pick_place": "box/top", "wiping": "sponge/handle"}  # what the grasping hand goes for
GRASP_DEPTH_M = {"pick_place": 0.025, "wiping": 0.0}
SECONDS = {"pick_place": 9.0, "wiping": 12.5}  # the demonstrations last up to 7.7 s / 11.6 s
CONTACT_M = 0.005  # wiping: force control presses once the pad is within this of the plate
PRESS_ON_N = 0.5  # ... and the predicted press exceeds this
FINGER_MAX = 0.04  # m, each gripper finger's travel (shared/robots/workcell.urdf)
PAD_CLEAR_M = 0.005  # the open gripper's pads clear the demonstrated grasp width by this on each side


@dataclass
class CarryResult:
    task: str
    seed: int
    demo: int
    grasp_hand: str  # the teacher's
    chosen_hand: str  # the hand that grasped in the policy's look-ahead (drives the gripper)
    success: bool
    outcome: dict  # the world's physical test (pick_place: offset_mm; wiping: coverage, peak_force_n)
    released: bool  # the gripper is open at the end (pick_place's test asks for it)
    seconds: float
    tracking_mm: float  # median distance of the robot's mapped points to the policy's goals
    solves_rejected: int
    object_motion_mm: float  # how far the grasped object moved from its start
    closest_mm: float  # closest approach of the gripper's pads to the grasp point
    max_grasp_kpa: float  # largest predicted grasping thumb + index pressure
    max_press_n: float  # largest commanded downward force (wiping)

    def to_dict(self) -> dict:
        return dict(self.__dict__)


def carried_weight(sim: WorldSim, joint: str) -> float:
    """N: the weight of everything the vertical axis ``joint`` carries (its body's subtree in the
    MuJoCo model), what its drive must hold when its position loop is off."""
    m = sim.model
    return float(m.body_subtreemass[m.jnt_bodyid[m.joint(joint).id]] * -m.opt.gravity[2])


def execute_carry(model, task: str, seed: int, demo: int, anchors: CarryAnchors | None = None,
                  feedback: bool = True, catch_m: float | None = 0.03, seconds: float | None = None,
                  plan_period_s: float = 0.1, knots: int = 20, horizon_s: float = 1.0) -> CarryResult:
    """Runs layout ``demo`` of ``task``'s protocol for ``seed`` with the robot in the loop; ``model``
    a trained Policy or None (the teacher's own hands). ``feedback``/``catch_m`` as in
    evaluation.execute.execute_layout."""
    if task not in CARRY_TASKS:
        raise ValueError(f"no carry loop for task {task!r} (carry tasks: {', '.join(CARRY_TASKS)})")
    sim = WorldSim(task, seed=seed, width=32, height=24)  # cameras unused
    sim.start_demo(demo)
    hands = sim.hand_keypoints()
    sim.set_robot_mode("robot")
    robot = load_robot(ROBOT.name)
    opt = TrajectoryOptimizer(robot, TrajoptConfig(knots=knots, point_map=ROBOT.execution_point_map, contact_slots=8))
    board = BoardSim(sim.joint_names)
    runner = TeacherReplay(sim.teacher) if model is None else PolicyRunner(model)
    dt = runner.dt if model is None else model.dt
    opt_dt = horizon_s / knots
    steps = int(round((seconds or SECONDS[task]) / dt))
    plan_every = max(1, int(round(plan_period_s / dt)))
    physics_per_step = max(1, int(round(dt / sim.physics_dt)))
    depth = GRASP_DEPTH_M[task]
    names, objects = sim.object_keypoints()
    grasp_k = names.index(GRASP_POINT[task])
    held_object = [i for i, n in enumerate(names) if n.split("/")[0] == GRASP_POINT[task].split("/")[0]]
    start = objects[held_object].mean(axis=0)
    area = [names.index(f"plate/a{i}") for i in range(4)] if task == "wiping" else None
    hand_mask, obj_mask = np.ones((2, KEYPOINTS_PER_HAND), bool), np.ones(len(names), bool)
    look = runner.horizon(SceneObs(hands, hand_mask, objects, obj_mask), int(round(LOOKAHEAD_S / dt)))
    look_h = look[:, :2 * KEYPOINTS_PER_HAND].reshape(len(look), 2, KEYPOINTS_PER_HAND, 3)
    g = int(np.argmin(np.linalg.norm(pinch(look_h) - objects[grasp_k], axis=-1).min(axis=0)))
    grasp_hand = HAND_NAMES[g]
    q, _ = sim.joint_state()
    wrist = robot.joint_names.index(ROLES.gripper_wrist)
    flipped = gripper_flipped(look_h[:, g, FINGERTIPS["thumb"]], look_h[:, g, FINGERTIPS["index"]], float(q[wrist]),
                              float(robot.upper[wrist]))
    plan_names = hand_point_names(grasp_hand, flipped) + list(names)
    n = len(sim.joint_names)
    z = sim.joint_names.index(ROLES.gripper_lift)
    fingers = [sim.joint_names.index(j) for j in ROLES.gripper_joints]
    tips = [opt.point_names.index(p) for p in ROLES.gripper_points]
    finger = opt.point_names.index(ROLES.press_point)
    finger_home = opt.points(q)[finger]
    dq = np.zeros(n)
    dq[z] = 0.01
    down = float(np.sign(opt.points(q)[tips[0], 2] - opt.points(q + dq)[tips[0], 2]))  # + effort lowers it?
    hold = -down * carried_weight(sim, ROLES.gripper_lift)  # force control holds the carriage's own weight
    current, t_current = np.repeat(q[None], knots, axis=0), 0.0
    state = CarryState()
    observing = feedback and catch_m is None
    squeeze, pressing, squeeze_since, grip = False, False, 0.0, 1.0
    rejected, tracking, frame = 0, [], 0
    closest, max_kpa, max_press = np.inf, 0.0, 0.0
    for k in range(steps):
        t = sim.time
        _, objects = sim.object_keypoints()
        pads = opt.points(sim.joint_state()[0])[tips].mean(axis=0)
        if feedback and k:
            # the robot's pads are where the policy's (lowered) pinch would be: observed back at the hand's height
            hands, observing = observed_hands(hands, g, pads + [0.0, 0.0, depth], observing, catch_m)
        stepped = runner.step(SceneObs(hands, hand_mask, objects, obj_mask))
        hands = stepped[:2 * KEYPOINTS_PER_HAND].reshape(2, KEYPOINTS_PER_HAND, 3)
        if k % plan_every == 0:
            horizon = runner.horizon(None, int(round(horizon_s / dt)) + 1, dt)
            horizon[:, g * KEYPOINTS_PER_HAND:(g + 1) * KEYPOINTS_PER_HAND, 2] -= depth  # the robot's grasp depth
            if anchors is not None:
                horizon = carry_horizon(horizon, g, anchors, objects, names, state, pads,
                                        objects[area] if area else None, depth)
            plan = PlanArrays(t, dt, plan_names, horizon, np.ones(horizon.shape[:2], bool))
            goals, mask = goals_for_horizon(plan, opt.point_names, t, opt_dt, knots)
            goals[:, finger], mask[:, finger] = finger_home, True  # the other hand parks: the finger stays home
            shift = max(0, min(knots - 1, round((t - t_current) / opt_dt)))
            goals, current, ok = receding_solve(opt, current, goals, mask, shift, opt_dt)
            t_current = t
            rejected += not ok
            reached = opt.points(sim.joint_state()[0])
            tracking.append(float(np.median(np.linalg.norm(reached - goals[0], axis=-1)[mask[0]])))
        effort = np.zeros(n)
        kpa = float(runner.efforts[g, THUMB] + runner.efforts[g, INDEX])
        max_kpa = max(max_kpa, kpa)
        grasp_at = objects[grasp_k] - [0.0, 0.0, depth] + (anchors.grasp_offset if anchors is not None else 0.0)
        near = float(np.linalg.norm(grasp_at - pads))
        closest = min(closest, near)
        if anchors is None:  # 7.2.10 as it is: predicted touch above GRASP_KPA squeezes, proportionally
            squeeze = kpa > GRASP_KPA
            if squeeze:
                effort[fingers] = -EFFORT_N_PER_KPA * kpa
            grip = 1.0
        else:  # predicted touch says when, the demonstrations how hard; closes only on the grasp point
            if state.held and near > LOST_M:  # slipped out: back to reaching
                state.held = False
            was = squeeze
            touch = touch_switch(squeeze, kpa, anchors.grasp_kpa)
            state.released = state.released or (state.held and not touch)
            squeeze = touch and not state.released and (state.held or near < HOLD_M)
            squeeze_since = t if squeeze and not was else squeeze_since
            grip = min(1.0, (t - squeeze_since) / TOUCH_RAMP_S)
            if squeeze:
                effort[fingers] = -EFFORT_N_PER_KPA * anchors.grasp_kpa * grip
            state.closing = squeeze and not state.held
            state.held = squeeze and (state.held or (t - squeeze_since >= GRIP_SETTLE_S and near < HOLD_M))
        press = 0.0
        if area is not None:  # wiping: the predicted press, force-controlled once the pad is near the plate
            predicted = float(runner.efforts[g, list(PRESS_REGIONS)].sum()) / KPA_PER_N
            pad = objects[names.index("sponge/bottom")]
            surface = float(objects[area, 2].mean())
            near_plate = over_area(pad, objects[area], CONTACT_MARGIN_M) and pad[2] - surface < CONTACT_M
            if anchors is None:
                pressing = near_plate and predicted > PRESS_ON_N
                press = predicted if pressing else 0.0
            else:
                pressing = near_plate and touch_switch(pressing, predicted, anchors.press_n)
                press = anchors.press_n if pressing else 0.0
            max_press = max(max_press, press)
        modes = np.full(n, Mode.POSITION, np.uint8)
        stiffness, damping = np.zeros(n), np.zeros(n)
        if press > 0.0:  # force in z: no stiffness, the carriage's weight held by feed-forward
            modes[z], damping[z] = Mode.IMPEDANCE, axis_params(sim.joint_names[z]).kd
            effort[z] = hold + down * press
        for sub in range(physics_per_step):
            if sub % FRAME_EVERY == 0:
                q_cmd, v_cmd = sample_trajectory(current, (sim.time - t_current) / opt_dt, opt_dt)
                if squeeze:
                    q_cmd[fingers] *= 1.0 - grip
                elif anchors is not None and not state.held:  # open at least as wide as the grasp
                    q_cmd[fingers] = np.maximum(q_cmd[fingers], min(FINGER_MAX, anchors.grasp_width_m / 2
                                                                    + PAD_CLEAR_M))
                board.receive(CommandFrame(frame, modes, q_cmd, v_cmd, effort, stiffness, damping), sim.time)
                frame += 1
            physics_step(sim, board)
    _, truth = sim.object_keypoints()
    world = sim.task_success()
    released = not squeeze
    success = bool(world["success"]) and (released or task != "pick_place")
    return CarryResult(task, seed, demo, sim.teacher.grasp_hand, grasp_hand, success,
                       {k: (float(v) if isinstance(v, (int, float, np.floating)) and not isinstance(v, bool) else v)
                        for k, v in world.items()}, released, sim.time,
                       float(np.nanmedian(tracking) * 1e3) if tracking else float("nan"), rejected,
                       float(np.linalg.norm(truth[held_object].mean(axis=0) - start) * 1e3), closest * 1e3,
                       max_kpa, max_press)
