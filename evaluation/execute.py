"""Robot in the loop (`xm eval --execute`): the learned policy drives the simulated workcell robot on
the validation layouts and the world judges the result.

One process, the same parts as the running cell without the transport: the world's MuJoCo model
in robot mode with the layout of a validation demonstration, the policy stepped at its sample
period (hands from its own prediction, objects observed from the world's truth: the interactive
neural simulation of 7.6.1), the trajectory optimizer of 7.4 replanning on every plan, and the
simulated control board (position mode, watchdog, limits) stepped with the physics. Success is
the world's assembly test (camera module seated on the board's connector, board lifted).

Roles, not sides: the workcell has its gripper on the left arm and a pressing finger on the right
(the arms share one rail and cannot cross), so the hand the policy grasps with drives the gripper
and the other hand's index tip drives the finger. Which hand grasps is read from the policy's own
neural simulation of the first seconds (the hand whose pinch comes closest to the module).
Predicted touch becomes effort (7.2.10): grasping thumb + index pressure shuts the gripper,
pressing index pressure pushes the finger down. ``TeacherReplay`` runs the same loop on the
teacher's own hands: what the cell achieves with a perfect policy.

Contact anchors (``anchors``, evaluation/anchors.py; ``anchored_horizon``): the contacts every
training demonstration makes close the last centimetres the policy leaves. Reaching, its pinch is
pulled onto the observed grasp point and turned square to it; predicted touch then closes the
gripper there (on/off with hysteresis, at the demonstrated force) and it dwells until the grip
settles; holding, the module is turned to the demonstrated heading against the board, its
intended placement shifted over the board's connector (eased in), docked there by servoing the
observed connectors together, pressed home by the gripper, and only then the policy's own lift
passes again, raised where it falls short of the demonstrations' lift (the lift anchor). The
policy still chooses the hand, the path and the timing of the grasp.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from evaluation.anchors import (
    MATED_DZ_M,
    MATED_M,
    AnchorState,
    ContactAnchors,
    anchored_horizon,
    heading,
    pinch,
)
from services.policy.runner import PolicyRunner, SceneObs
from services.robot.board_sim import BoardSim, axis_params
from services.trajopt.mapping import PlanArrays, goals_for_horizon
from services.trajopt.optimizer import TrajectoryOptimizer, TrajoptConfig
from services.world.model import ASSEMBLY_TASKS
from services.world.sim import WorldSim
from services.world.teacher import KPA_PER_N, Teacher
from shared.demo import FINGERTIPS, HAND_NAMES, KEYPOINTS_PER_HAND, TACTILE_REGIONS
from shared.kinematics import load_robot
from shared.protocols.robot_board import CommandFrame, Mode
from shared.robots.registry import DEFAULT_ROBOT, describe

ROBOT = describe(DEFAULT_ROBOT)  # the evaluated robot: its grasp roles say which arm grasps, which presses
ROLES = ROBOT.grasp
GRIPPER_JOINTS = ROLES.gripper_joints
PRESS_JOINT = ROLES.press_joint  # positive effort pushes the finger down
GRIPPER_Z = ROLES.gripper_lift
GRIPPER_HAND = ROLES.gripper_points[0].split("/")[0]  # the plan hand whose points the gripper executes
PRESS_BESIDE_M = 0.08  # a finger goal this close (xy) to the gripper's: the gripper presses instead
THUMB, INDEX = TACTILE_REGIONS.index("thumb"), TACTILE_REGIONS.index("index")
THUMB_TIP, INDEX_TIP = FINGERTIPS["thumb"], FINGERTIPS["index"]
GRASP_KPA = 10.0  # the teacher's grasp reads 2 x 20 kPa on thumb and index; 10 kPa = a quarter of it
# the learned policy alone: its predicted grasping touch shuts the gripper above 3 kPa and lets go
# below half of that. In the loop the net predicts 11-20 kPa at most, a quarter to a half of its
# open loop: the loop shows it the lens its demonstrations hide under the holding hand
LEARNED_GRASP_KPA = 3.0
EFFORT_N_PER_KPA = 0.1  # kPa over a ~1 cm^2 fingertip -> N
LEAD_IN_FRAME_SETS = 5  # reconstructed objects: frame sets recon sees before the robot starts
LOOKAHEAD_S = 9.0  # neural simulation that decides the grasping hand and the gripper's finger order
FRAME_EVERY = 2  # physics steps (2 ms) per command frame
PRESS_WEIGHT = 0.1  # the finger yields to the gripper where the two arms compete for room on the rail
HOLD_M = 0.008  # the gripper holds the module: shut, with the grasp point this close to its pads
LOST_M = 0.02  # ... and has lost it when the point is this far from them
# of the demonstrated pressure: predicted touch switches contact on / off (the nets predict 10-25 % of the
# demonstrated peak at a grasp; at 0.1 a weakly predicted mirrored grasp never closed)
TOUCH_ON, TOUCH_OFF = 0.05, 0.025
TOUCH_RAMP_S = 0.3  # the demonstrations' grasp force ramps in over 0.3 s
GRIP_SETTLE_S = 0.6  # held once shut this long on the grasp point (the gripper dwells there until then)
MATED_PRESS_S = 0.2  # mated: pressed home for 0.2 s while aligned


def hand_point_names(grasp_hand: str, flipped: bool = False) -> list[str]:
    """Plan names for the policy's hands (left block, then right) so that the grasping hand maps
    to the robot's gripper (GRIPPER_HAND) and the pressing hand to its finger; ``flipped``
    swaps the grasping thumb and index (see gripper_flipped)."""
    other = next(h for h in HAND_NAMES if h != GRIPPER_HAND)
    sides = (GRIPPER_HAND, other) if grasp_hand == HAND_NAMES[0] else (other, GRIPPER_HAND)
    names = [f"{h}/{k}" for h in sides for k in range(KEYPOINTS_PER_HAND)]
    if flipped:  # the gripper's two fingers trade their goals
        a, b = (names.index(p) for p in ROLES.gripper_points)
        names[a], names[b] = names[b], names[a]
    return names


def sample_trajectory(q: np.ndarray, s: float, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Position (linear between knots) and velocity of a knot trajectory (knots, n) at knot time s."""
    s = float(np.clip(s, 0, len(q) - 1))
    i = int(s)
    j = min(i + 1, len(q) - 1)
    return q[i] + (s - i) * (q[j] - q[i]), (q[j] - q[i]) / dt


def gripper_flipped(thumb: np.ndarray, index: np.ndarray, wrist0: float = 0.0,
                    limit: float = 2 * np.pi) -> bool:
    """thumb, index (T,3): the grasping hand's tips over a look-ahead. The parallel gripper is
    symmetric, so the thumb may drive either finger; True when driving finger b keeps the wrist
    (yaw = thumb->index angle + 90 deg, or - 90 deg flipped) further inside its travel (+-limit)
    when the unflipped one would come within 0.2 rad of it.
    Decided once per run: flipping while holding the module would turn it over."""
    d = index - thumb
    phi = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
    worst = []
    for offset in (np.pi / 2, -np.pi / 2):
        theta = phi + offset
        theta += 2 * np.pi * np.round((wrist0 - theta[0]) / (2 * np.pi))  # start from the wrist's turn
        worst.append(np.abs(theta).max())
    return bool(worst[1] < worst[0] and worst[0] > limit - 0.2)


def observed_hands(hands: np.ndarray, g: int, pads: np.ndarray, observing: bool,
                   catch_m: float | None) -> tuple[np.ndarray, bool]:
    """Hand feedback: ``hands`` (2,21,3) with the grasping hand ``g`` moved rigidly so its pinch lies
    between the gripper's ``pads`` (3,), once observing; and whether it is. Observing starts when
    the pads first come within ``catch_m`` of the hand's own pinch (None: at once) and then stays."""
    miss = pads - pinch(hands[g])
    observing = observing or catch_m is None or float(np.linalg.norm(miss)) < catch_m
    if not observing:
        return hands, False
    out = hands.copy()
    out[g] += miss
    return out, True


def grasping_hand(hands: np.ndarray, lens: np.ndarray) -> str:
    """hands (T,2,21,3) of a rollout, lens (3,) the module: the hand whose thumb-index midpoint
    comes closest to the module."""
    return HAND_NAMES[int(np.argmin(np.linalg.norm(pinch(hands) - lens, axis=-1).min(axis=0)))]


class TeacherReplay:
    """The teacher's hands and glove pressure in place of the policy (same interface as
    PolicyRunner): the upper bound of execution, and a check that the cell can do the task."""

    def __init__(self, teacher: Teacher, dt: float = 0.02) -> None:
        self.teacher, self.dt, self.t = teacher, dt, 0.0
        self.efforts = np.zeros((2, len(TACTILE_REGIONS)))
        self.scene: SceneObs | None = None

    def _state(self, t: float):
        return self.teacher.state(min(t, self.teacher.duration))

    def step(self, scene: SceneObs) -> np.ndarray:
        self.scene = scene
        self.t += self.dt
        st = self._state(self.t)
        self.efforts = st.forces * KPA_PER_N  # as the glove reports
        return np.concatenate([st.hands.reshape(-1, 3), scene.objects])

    def horizon(self, scene: SceneObs | None, steps: int, dt: float | None = None) -> np.ndarray:
        if scene is not None:
            self.scene = scene
        dt = dt or self.dt
        return np.stack([np.concatenate([self._state(self.t + (i + 1) * dt).hands.reshape(-1, 3),
                                         self.scene.objects]) for i in range(steps)])


@dataclass
class ExecutionResult:
    seed: int
    demo: int
    grasp_hand: str  # the teacher's
    chosen_hand: str  # the hand the policy grasped with in its look-ahead (drives the gripper)
    success: bool
    seconds: float  # simulated
    tracking_mm: float  # median distance of the robot's mapped points to the policy's goals
    solves_rejected: int
    object_motion_mm: float  # how far the camera module moved from its start
    closest_mm: float  # closest approach of the gripper's finger-tip midpoint to the module's lens point
    opening_mm: float  # gripper finger opening (sum of both fingers) at that moment
    max_grasp_kpa: float  # largest predicted grasping thumb + index pressure (7.2.10), 0 without tactile
    connector_gap_mm: float  # closest approach of the module's connector to the board's (seated under 3)
    seated: bool  # the connector snapped home (pressed while aligned)
    policy_closest_mm: float = float("nan")  # closest approach of the policy's own grasping pinch to the lens

    def to_dict(self) -> dict:
        return dict(self.__dict__)



def anchored_press(was: bool, aligned: bool, docking: bool, kpa: float, demonstrated_kpa: float) -> bool:
    """With contact anchors: the aligned mate presses; elsewhere predicted touch (``kpa``) decides,
    except while the held module is docking: a push then pins it to the board short of its target."""
    return aligned or (not docking and touch_switch(was, kpa, demonstrated_kpa))


def touch_switch(on: bool, kpa: float, demonstrated_kpa: float) -> bool:
    """Contact from predicted pressure, with hysteresis: on above TOUCH_ON of the demonstrated
    pressure, off again only below TOUCH_OFF of it (a prediction that wavers near one threshold
    would open the gripper mid-carry)."""
    return kpa > (TOUCH_OFF if on else TOUCH_ON) * demonstrated_kpa


def learned_squeeze(on: bool, kpa: float, grasp_kpa: float | None) -> bool:
    """Without anchors: shut above ``grasp_kpa`` of predicted grasping touch, open again only below
    half of it (a prediction wavering near one threshold would drop the module mid-carry)."""
    return grasp_kpa is not None and kpa > (0.5 * grasp_kpa if on else grasp_kpa)


def physics_step(sim: WorldSim, board: BoardSim) -> None:
    """One physics step of the cell under the simulated board's control loop."""
    q, qd = sim.joint_state()
    efforts, _ = board.step(sim.time, q, qd, sim.physics_dt)
    sim.set_efforts(efforts)
    sim.step(1)


def receding_solve(opt: TrajectoryOptimizer, current: np.ndarray, goals: np.ndarray, mask: np.ndarray,
                   shift: int, opt_dt: float) -> tuple[np.ndarray, np.ndarray, bool]:
    """One receding-horizon step: the goals clipped into the gantry's reach (the optimizer rejects
    goals outside it), the last solution shifted by ``shift`` knots as the warm start, one solve.
    Returns the clipped goals, the joint trajectory to keep and whether the solve succeeded."""
    goals = np.clip(goals, opt.reach_lo[None] + 1e-3, opt.reach_hi[None] - 1e-3)
    if shift:
        current = np.concatenate([current[shift:], np.repeat(current[-1:], shift, 0)])
    result = opt.solve(current, goals, mask, opt_dt)
    return goals, (result.q if result.ok else current), bool(result.ok)


def execute_layout(model, seed: int, demo: int, seconds: float = 9.0, plan_period_s: float = 0.1,
                   knots: int = 20, horizon_s: float = 1.0, grasp_kpa: float | None = LEARNED_GRASP_KPA,
                   feedback: bool = False, anchors: ContactAnchors | None = None,
                   horizon_dt: float | None = None, catch_m: float | None = None, observer=None,
                   start_hands: np.ndarray | None = None, task: str = "assembly",
                   glove: np.ndarray | None = None) -> ExecutionResult:
    """Runs one validation layout (``assembly_protocol(seed)[demo]``) with the robot in the loop.

    ``task``: "assembly" or "latch" (the same layouts; the latch's snap-fit engages only at 5 N).

    ``model``: a trained Policy, or None for the teacher's own hands (TeacherReplay).
    ``grasp_kpa``: without anchors, above this predicted grasping thumb + index pressure the gripper
    is commanded shut with an effort proportional to it, and opened again below half of it
    (``learned_squeeze``; None: fingers follow the mapped thumb and index only).
    ``feedback``: the robot's own points are observed as the policy's hands (7.6.8: the robot's
    end-effector keypoints are detected like the objects'): each step the grasping hand is moved
    rigidly so its pinch lies between the gripper's pads, instead of the policy running on its own
    predicted hands.
    ``anchors``: contact anchors mined from the training demonstrations (evaluation/anchors.py):
    the grasping hand's goals are pulled onto the observed grasp point while reaching, and once the
    module is held, onto the placement that brings its mate point to the observed target.
    ``horizon_dt``: the step of the policy's horizon rollouts (default its sample period; the
    optimizer's knot spacing, 7.16's keyframes, takes 2.5 times fewer network passes but measured
    10 / 12 against 12 / 12 on seed 1).
    ``catch_m``: with feedback, the grasping hand is observed at the gripper only from when the pads
    first come this close to the policy's own pinch (None: from the first step). The gripper starts
    where no demonstrated hand was; until it has caught up with the policy's hand it follows the
    policy's own prediction.
    ``observer``: a CellObserver (evaluation/reconstructed.py): the policy and the anchors see the
    objects as recon reconstructs them from rendered frame sets at the camera rate, and between
    frame sets the policy runs on its own object predictions; None: the world's truth every step.
    ``glove``: (2,) the hands on which the policy is given its own predicted touch as a glove's
    reading (default none: the robot reads no touch, and training gives a hand without a glove none;
    given back on both hands, the latch's snap never engaged on the layouts where it did without).
    ``start_hands``: the policy's initial hands (default the teacher's true start pose). Success and
    the recorded distances are always measured on the world's truth."""
    if task not in ASSEMBLY_TASKS:
        raise ValueError(f"execute_layout runs {ASSEMBLY_TASKS}, not {task!r} (execute_carry.py runs the others)")
    sim = WorldSim(task, seed=seed, width=32, height=24)  # cameras unused here
    sim.start_demo(demo)
    if start_hands is None:
        start_hands = sim.hand_keypoints()  # the teacher's pose at the start: the policy's initial hands
    sim.set_robot_mode("robot")
    robot = load_robot(ROBOT.name)
    opt = TrajectoryOptimizer(robot, TrajoptConfig(knots=knots, point_map=ROBOT.execution_point_map, contact_slots=8,
                                                   point_weights={ROLES.press_point: PRESS_WEIGHT}))
    board = BoardSim(sim.joint_names)
    runner = TeacherReplay(sim.teacher) if model is None else PolicyRunner(model, glove)
    dt = runner.dt if model is None else model.dt
    opt_dt = horizon_s / knots
    steps = int(round(seconds / dt))
    plan_every = max(1, int(round(plan_period_s / dt)))
    h_dt = horizon_dt or dt
    physics_per_step = max(1, int(round(dt / sim.physics_dt)))
    names, objects = sim.object_keypoints()
    cam = [i for i, n in enumerate(names) if n.startswith("camera/")]
    cam0 = objects[cam].mean(axis=0)
    hand_mask = np.ones((2, KEYPOINTS_PER_HAND), bool)
    obj_mask = np.ones(len(names), bool)
    if observer is not None:
        for _ in range(LEAD_IN_FRAME_SETS):  # recon has watched the cell before the robot starts
            observer.frame_set(sim)
        objects, obj_mask, predicted_objects = observer.objects.copy(), observer.mask.copy(), None
    hands = start_hands
    look = runner.horizon(SceneObs(hands, hand_mask, objects, obj_mask), int(round(LOOKAHEAD_S / dt)))
    grasp_hand = grasping_hand(look[:, :2 * KEYPOINTS_PER_HAND].reshape(len(look), 2, KEYPOINTS_PER_HAND, 3),
                               objects[names.index("camera/lens")])
    g, p = HAND_NAMES.index(grasp_hand), 1 - HAND_NAMES.index(grasp_hand)
    look_g = look[:, g * KEYPOINTS_PER_HAND:(g + 1) * KEYPOINTS_PER_HAND]
    wrist = robot.joint_names.index(ROLES.gripper_wrist)
    flipped = gripper_flipped(look_g[:, THUMB_TIP], look_g[:, INDEX_TIP], float(sim.joint_state()[0][wrist]),
                              float(robot.upper[wrist]))
    plan_names = hand_point_names(grasp_hand, flipped) + list(names)
    press = sim.joint_names.index(PRESS_JOINT)
    gripper_z = sim.joint_names.index(GRIPPER_Z)
    q, _ = sim.joint_state()
    current, t_current = np.repeat(q[None], knots, axis=0), 0.0
    finger_home = opt.points(q)[opt.point_names.index(ROLES.press_point)]
    n = len(sim.joint_names)
    success, rejected, tracking = False, 0, []
    fingers = [sim.joint_names.index(j) for j in GRIPPER_JOINTS]
    tips = [opt.point_names.index(p) for p in ROLES.gripper_points]
    finger = opt.point_names.index(ROLES.press_point)
    lens = names.index("camera/lens")
    closest, opening, max_kpa, min_gap, policy_closest = np.inf, np.nan, 0.0, np.inf, np.inf
    frame, press_beside = 0, False
    observing = feedback and catch_m is None  # the grasping hand is observed at the gripper
    squeeze, pressing, squeeze_since, grip = False, False, 0.0, 1.0
    if anchors is not None:
        grasp_k, mate_k, target_k = (names.index(n) for n in (anchors.grasp_point, anchors.mate_point,
                                                                 anchors.mate_target))
        target_object = [i for i, n in enumerate(names) if n.split("/")[0] == anchors.mate_target.split("/")[0]]
        anchor_state = AnchorState(grasp_k, mate_k, target_k, target_object, observing)
    for k in range(steps):
        t = sim.time
        seen_objects, seen_mask = objects, obj_mask
        if observer is None:
            _, objects = sim.object_keypoints()
            seen_objects = objects
        else:
            if observer.update(sim):
                objects = seen_objects = observer.objects.copy()
            elif predicted_objects is not None:  # no new frame set: the objects as the policy predicts them
                seen_objects = predicted_objects
            seen_mask = observer.mask
        # the policy's own next hands (runner.state keeps the observation it was given)
        if feedback and k:
            hands, observing = observed_hands(hands, g, opt.points(sim.joint_state()[0])[tips].mean(axis=0),
                                              observing, catch_m)
            if anchors is not None:
                anchor_state.observed_hand = observing
        stepped = runner.step(SceneObs(hands, hand_mask, seen_objects, seen_mask))
        hands = stepped[:2 * KEYPOINTS_PER_HAND].reshape(2, KEYPOINTS_PER_HAND, 3)
        predicted_objects = stepped[2 * KEYPOINTS_PER_HAND:]
        policy_closest = min(policy_closest, float(np.linalg.norm(
            pinch(hands[g]) - objects[lens])))
        if k % plan_every == 0:
            horizon = runner.horizon(None, int(round(horizon_s / h_dt)) + 1, h_dt)
            if anchors is not None:
                robot_tips = opt.points(sim.joint_state()[0])[tips]
                horizon = anchored_horizon(horizon, g, anchors, objects, anchor_state, robot_tips.mean(axis=0),
                                           heading(robot_tips[1] - robot_tips[0]), flipped,
                                           max(1, round(plan_period_s / h_dt)), h_dt)
            # sample i is the state at t + (i + 1) h_dt; stamped one policy period early, as always
            plan = PlanArrays(t + h_dt - dt, h_dt, plan_names, horizon, np.ones(horizon.shape[:2], bool))
            goals, mask = goals_for_horizon(plan, opt.point_names, t, opt_dt, knots)
            # the finger yields where it would work beside the gripper: on one rail the carriages
            # cannot come that close, and the gripper then presses instead (below)
            beside = np.linalg.norm(goals[:, finger, :2] - goals[:, tips, :2].mean(axis=1), axis=-1) < PRESS_BESIDE_M
            mask[:, finger] &= ~beside
            if anchors is not None and anchor_state.held and not anchor_state.mated:
                # the gripper places and presses itself: the finger goes home, out of its way (a
                # finger merely left without a goal stays put, and its carriage blocks the gripper)
                goals[:, finger], mask[:, finger] = finger_home, True
            press_beside = bool(beside[0])
            shift = max(0, min(knots - 1, round((t - t_current) / opt_dt)))
            goals, current, ok = receding_solve(opt, current, goals, mask, shift, opt_dt)
            t_current = t
            rejected += not ok
            q_now, _ = sim.joint_state()
            reached = opt.points(q_now)
            tracking.append(float(np.median(np.linalg.norm(reached - goals[0], axis=-1)[mask[0]]))
                            if mask[0].any() else np.nan)
        effort = np.zeros(n)
        kpa = float(runner.efforts[g, THUMB] + runner.efforts[g, INDEX])
        max_kpa = max(max_kpa, kpa)
        if anchors is None:
            squeeze = learned_squeeze(squeeze, kpa, grasp_kpa)  # 7.2.10: predicted touch becomes squeeze
            if squeeze:
                effort[fingers] = -EFFORT_N_PER_KPA * kpa
        else:  # predicted touch says when, the demonstrations how hard (on/off with hysteresis); the
            # gripper closes only on the grasp point, dwells there while it closes, and a grip that
            # loses the point is let go (back to reaching)
            pads = opt.points(sim.joint_state()[0])[tips].mean(axis=0)
            near = np.linalg.norm(objects[grasp_k] - pads)
            if anchor_state.held and near > LOST_M:
                anchor_state.let_go()
            was = squeeze
            squeeze = touch_switch(squeeze, kpa, anchors.grasp_kpa) and (anchor_state.held or near < HOLD_M)
            squeeze_since = t if squeeze and not was else squeeze_since
            grip = min(1.0, (t - squeeze_since) / TOUCH_RAMP_S)
            if squeeze:  # ramped in like the demonstrations' grasp force: shut at once, it flicks the lens away
                effort[fingers] = -EFFORT_N_PER_KPA * anchors.grasp_kpa * grip
            anchor_state.closing = squeeze and not anchor_state.held
            anchor_state.held = anchor_state.held or (squeeze and t - squeeze_since >= GRIP_SETTLE_S
                                                      and near < HOLD_M)
        # ... and push: with the finger, or where the finger would press beside the gripper (the
        # two carriages cannot come that close on their rail) with the gripper on what it holds
        # (impedance mode on that axis while pushing: the position loop's integral would undo the push)
        push = EFFORT_N_PER_KPA * max(0.0, float(runner.efforts[p, INDEX]))
        pusher = gripper_z if press_beside else press
        if anchors is not None:
            # the mate anchor presses where the demonstrations pressed: on the aligned mate, with the
            # gripper (the finger cannot come beside it on the rail); elsewhere predicted touch decides
            gap = objects[mate_k] - objects[target_k] - anchors.mate_offset
            aligned = (anchor_state.held and not anchor_state.mated and np.linalg.norm(gap[:2]) < MATED_M
                       and abs(gap[2]) < MATED_DZ_M)  # pressed home: the push ends, or it fights the lift
            pressing = anchored_press(pressing, aligned, anchor_state.held and not anchor_state.mated,
                                      float(runner.efforts[p, INDEX]), anchors.press_kpa)
            push = EFFORT_N_PER_KPA * anchors.press_kpa if pressing else 0.0
            pusher = gripper_z if aligned else pusher
            anchor_state.pressed_s = anchor_state.pressed_s + dt if aligned else 0.0
            anchor_state.mated = anchor_state.mated or anchor_state.pressed_s >= MATED_PRESS_S
            anchor_state.mated_s = anchor_state.mated_s + dt if anchor_state.mated else 0.0
        effort[pusher] = push
        modes = np.full(n, Mode.POSITION, np.uint8)
        stiffness, damping = np.zeros(n), np.zeros(n)
        if push > 0.5:
            gains = axis_params(sim.joint_names[pusher])  # the axis's own position-loop gains
            modes[pusher], stiffness[pusher], damping[pusher] = Mode.IMPEDANCE, gains.kp, gains.kd
        for sub in range(physics_per_step):
            if sub % FRAME_EVERY == 0:  # a frame every 4 ms, well inside the board's 10 ms watchdog
                q_cmd, v_cmd = sample_trajectory(current, (sim.time - t_current) / opt_dt, opt_dt)
                if squeeze:
                    q_cmd[fingers] *= 1.0 - grip
                board.receive(CommandFrame(frame, modes, q_cmd, v_cmd, effort, stiffness, damping), sim.time)
                frame += 1
            physics_step(sim, board)
        success = success or sim.assembly_success()
        if k % plan_every == 0:
            q_now, _ = sim.joint_state()
            _, truth = sim.object_keypoints()  # the record measures the world, not the observation
            gap = float(np.linalg.norm(opt.points(q_now)[tips].mean(axis=0) - truth[lens]))
            if gap < closest:
                closest, opening = gap, float(q_now[fingers].sum())
            min_gap = min(min_gap, sim.connector_gap())
    _, truth = sim.object_keypoints()
    return ExecutionResult(seed, demo, sim.teacher.grasp_hand, grasp_hand, bool(success), sim.time,
                           float(np.nanmedian(tracking) * 1e3) if tracking else float("nan"), rejected,
                           float(np.linalg.norm(truth[cam].mean(axis=0) - cam0) * 1e3), closest * 1e3,
                           opening * 1e3, max_kpa, min_gap * 1e3, sim.seated_at is not None, policy_closest * 1e3)
