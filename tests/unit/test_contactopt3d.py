"""contactopt in 3-D: the URDF chain, the hand tasks' geometry and losses, the MuJoCo replay."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import yourdfpy

from contactopt import losses3d
from contactopt.handmodel import MODELS
from contactopt.kinematics import load_chain
from contactopt.policy import Policy
from contactopt.replay import replay, scene_xml
from contactopt.sim3d import BOTTOM, F64, GRAVITY, MASS, Step3D, policy_fn, rollout3d, scene
from contactopt.tasks import get_task
from contactopt.tasks3d import TASKS3D, task_residual3d

torch.set_num_threads(1)
LIFT, TURN, CYL = TASKS3D["lift"], TASKS3D["hand_turn"], TASKS3D["fixed_cylinder"]


def test_models_have_the_joint_counts_of_table_2_1() -> None:
    hand, arm = load_chain(MODELS / "hand.urdf"), load_chain(MODELS / "arm_hand.urdf")
    assert (hand.n_joints, hand.n_dof) == (24, 20)
    assert (arm.n_joints, arm.n_dof) == (30, 26)
    assert len(hand.sphere_names) == 5
    ff1 = hand.joint_names.index("FFJ1")
    assert hand.coupling[ff1, hand.dof_names.index("FFJ2")] == 1.0  # distal coupled to middle


def test_fingertips_match_yourdfpy_forward_kinematics() -> None:
    chain = load_chain(MODELS / "hand.urdf")
    robot = yourdfpy.URDF.load(str(MODELS / "hand.urdf"), load_meshes=False)
    rng = np.random.default_rng(0)
    dof = rng.uniform(-0.5, 1.0, chain.n_dof)
    q = chain.coupling @ torch.tensor(dof, dtype=F64)
    robot.update_cfg({n: float(v) for n, v in zip(chain.dof_names, dof, strict=True)})
    tips = chain.sphere_centers(q[None], torch.eye(4, dtype=F64))[0]
    for name, tip in zip(chain.sphere_names, tips, strict=True):
        link = name.removesuffix("_tip")
        expected = robot.get_transform(link) @ np.array([0.026 if link != "thdistal" else 0.0275, 0, 0, 1])
        assert tip.tolist() == pytest.approx(expected[:3].tolist(), abs=1e-9)


def test_unknown_model_and_task_list_what_exists() -> None:
    with pytest.raises(ValueError, match="hand.urdf"):
        load_chain(MODELS / "shadow.urdf")
    with pytest.raises(ValueError, match="fixed_cylinder"):
        get_task("flip_right")


def test_box_and_cylinder_signed_distance() -> None:
    pos, rot = torch.zeros(1, 3, dtype=F64), torch.eye(3, dtype=F64)[None]
    p = torch.tensor([[[0.05, 0.0, 0.0], [0.0, 0.0, 0.01]]], dtype=F64)
    d, n = losses3d.sdf_object(p, pos, rot, LIFT)
    assert d[0].tolist() == pytest.approx([0.025, -0.015])
    assert n[0, 0].tolist() == pytest.approx([1.0, 0.0, 0.0])
    assert n[0, 1].tolist() == pytest.approx([0.0, 0.0, 1.0])
    d, n = losses3d.sdf_object(torch.tensor([[[0.03, 0.04, 0.0]]], dtype=F64), pos, rot, CYL)
    assert float(d) == pytest.approx(0.05 - 0.025)
    assert n[0, 0].tolist() == pytest.approx([0.6, 0.8, 0.0])


def rest_step(force_table: float, tip_force: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> Step3D:
    """One step with the cube resting on the table, each table pair (bottom corner) pushing up
    with a quarter of force_table."""
    sc = scene(LIFT.robot)
    tips = sc.chain.sphere_centers(sc.q0[None], sc.base)
    pos = torch.tensor([[0.0, 0.0, 0.025]], dtype=F64)
    corners = (BOTTOM * 0.025 + pos)[None]
    anchor = torch.cat([tips, corners * torch.tensor([1.0, 1.0, 0.0], dtype=F64)], 1)
    p_b = torch.cat([torch.zeros(1, 5, 3, dtype=F64) + pos[:, None], corners], 1)
    force = torch.zeros(1, 9, 3, dtype=F64)
    force[0, 5:, 2] = force_table / 4
    force[0, 0] = torch.tensor(tip_force, dtype=F64)
    z = torch.zeros(1, 3, dtype=F64)
    eye = torch.eye(3, dtype=F64)[None]
    return Step3D(anchor, torch.zeros_like(anchor), pos, eye, z, z, anchor.clone(), p_b, force)


def test_resting_cube_is_consistent_and_a_distant_force_is_not() -> None:
    sc = scene(LIFT.robot)
    res = losses3d.residuals3d(rest_step(MASS * GRAVITY), LIFT, sc, losses3d.SCALES)
    assert all(float(r.abs().max()) < 1e-3 for r in res)  # every loss zero (norms smoothed at 0)
    # a 1 N force from the first fingertip, 12 mm off the cube: distance loss (2.10) and shape
    # loss (its object-side point, the cube's center, is inside; the finger-side one at the tip)
    res = losses3d.residuals3d(rest_step(MASS * GRAVITY, (-1.0, 0.0, 0.0)), LIFT, sc, losses3d.SCALES)
    assert float(res[1].abs().max()) > 1.0
    pulling = losses3d.residuals3d(rest_step(MASS * GRAVITY, (1.0, 0.0, 0.0)), LIFT, sc, losses3d.SCALES)
    assert float(pulling[2].max()) > 1.0  # a force pulling the cube towards the finger: off the cone


def test_table_below_zero_intersection() -> None:
    s = rest_step(0.0)
    s.pos = s.pos - torch.tensor([[0.0, 0.0, 0.004]], dtype=F64)  # sunk 4 mm into the table
    res = losses3d.residuals3d(s, LIFT, scene(LIFT.robot), losses3d.SCALES)
    assert float(res[4].max()) == pytest.approx(0.4)  # 4 mm in units of 1 cm


def test_fresh_policy_starts_at_rest_and_the_task_residual_is_the_goal() -> None:
    torch.manual_seed(0)
    for task in (LIFT, TURN):
        policy = losses3d.make_policy(task)
        with torch.no_grad():
            policy.net[2].weight.zero_()  # only the biases: the table carries the weight
            ro = rollout3d(policy_fn(tuple(policy.parameters()), task, scene(task.robot)), task,
                           torch.zeros(2, 2, dtype=F64))
        assert (ro.pos[:, -1] - ro.pos[:, 0]).abs().max() < 1e-9
        r = task_residual3d(task, ro.pos, ro.rot, ro.omega)
        expected = [0, 0, -5.0, 0, 0, 0] if task is LIFT else [0, 0, -1.0]
        assert r[0].tolist() == pytest.approx(expected, abs=1e-9)


def test_gradient_reaches_the_policy_through_the_predicted_forces() -> None:
    torch.manual_seed(0)
    policy = Policy(hidden=8, n_in=scene(TURN.robot).n_in(), n_out=scene(TURN.robot).n_out(TURN))
    params = tuple(p.requires_grad_(True) for p in policy.parameters())
    ro = rollout3d(policy_fn(params, TURN, scene(TURN.robot)), TURN, torch.zeros(2, 2, dtype=F64))
    loss = (task_residual3d(TURN, ro.pos, ro.rot, ro.omega) ** 2).sum()
    grads = torch.autograd.grad(loss, params)
    assert max(float(g.abs().max()) for g in grads) > 1e-6


def test_training_weights_the_force_distance_loss_and_the_criterion_does_not() -> None:
    """The objective weights Eq. 2.10 by DISTANCE_WEIGHT; the breakdown the success criterion
    reads reports every consistency loss at weight 1."""
    torch.manual_seed(0)
    policy = losses3d.make_policy(TURN)
    xy = torch.zeros(2, 2, dtype=F64)
    with torch.no_grad():
        ro = rollout3d(policy_fn(tuple(policy.parameters()), TURN, scene(TURN.robot)), TURN, xy)
        trained = [float((p ** 2).sum(1).mean()) for p in losses3d.residual_parts3d(ro, TURN)]
    report, _ = losses3d.loss_breakdown3d(policy, TURN, xy)
    at = 1 + list(losses3d.LOSSES).index("distance")
    assert report["distance"] > 0
    assert trained[at] == pytest.approx(losses3d.DISTANCE_WEIGHT * report["distance"])
    assert trained[at + 1] == pytest.approx(report["friction"])


@pytest.mark.parametrize("push", [0.0, 2.0])
def test_mujoco_replay_of_a_vertical_force(push: float) -> None:
    """No force: the cube stays on the table; twice its weight upward at the center: it rises
    g t^2 / 2 (within 2 %: MuJoCo's own time discretization and its soft contact at the start)."""
    xml = scene_xml("box", LIFT.half, 0.8, False, LIFT.dt)
    t = 10
    f = np.zeros((t, 1, 3))
    f[:, 0, 2] = push * MASS * GRAVITY
    pts = np.tile(np.array([0.0, 0.0, 0.025]), (t, 1, 1))
    pos, rot, omega, unstable = replay(xml, np.array([0.0, 0.0, 0.025]), f, pts, LIFT.dt, False)
    duration = t * LIFT.dt
    expected = 0.0 if push == 0 else 0.5 * (push - 1) * GRAVITY * duration ** 2
    assert pos[-1, 2] - pos[0, 2] == pytest.approx(expected, rel=0.02, abs=0.002)
    assert unstable == 0
    assert math.isclose(float(np.abs(omega).max()), 0.0, abs_tol=1e-3)
