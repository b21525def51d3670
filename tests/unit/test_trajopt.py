"""Trajectory optimizer on both robot models: tracking, limits, arm separation, hand-pose prior."""

from __future__ import annotations

import numpy as np

from services.trajopt.hand_prior import hand_pose_prior
from services.trajopt.optimizer import TrajectoryOptimizer, TrajoptConfig
from services.world.teacher import generate_demo
from shared.kinematics import load_robot

HAND_MAP = {"index_tip": "right/8", "thumb_tip": "right/4", "middle_tip": "right/12", "wrist_point": "right/0"}


def test_workcell_tracks_reachable_goals_within_limits_and_keeps_the_arms_apart():
    model = load_robot("workcell")
    opt = TrajectoryOptimizer(model, TrajoptConfig())
    K, n = 20, len(model.joint_names)
    q0 = np.zeros(n)
    q0[[2, 8]] = 0.2
    cur = np.repeat(q0[None], K, 0)
    # the right arm's finger asked to cross far into the left arm's side: separation must hold
    goals = np.repeat((opt.points(q0) + [[0.05, 0.05, -0.05], [0.05, 0.05, -0.05], [0.0, 0.45, 0.0]])[None], K, 0)
    solved = 0
    for _ in range(20):
        r = opt.solve(cur, goals, np.ones((K, 3), bool), 0.05)
        solved += r.ok  # a rejected solve keeps the executing trajectory (checked below)
        assert r.ok or (np.array_equal(r.q, cur) and "violation" in r.reason)
        cur = np.concatenate([r.q[1:], r.q[-1:]])
    assert solved >= 16 and r.ok
    q = r.q[-1]
    assert np.all(q >= model.lower - 1e-6) and np.all(q <= model.upper + 1e-6)
    np.testing.assert_allclose(opt.points(q)[:2], goals[-1][:2], atol=1e-3)  # reachable goals reached
    poses = model.fk(q)
    gap = poses["right_carriage"][1, 3] - poses["left_carriage"][1, 3]
    assert abs(gap) >= 0.08 - 1e-3  # carriage boxes (8 cm deep) plus clearance never overlap
    assert np.all(np.abs(np.diff(r.q, axis=0)) <= model.max_velocity * 0.05 + 1e-6)


def test_nan_goals_are_rejected_with_a_reason_and_the_last_trajectory_kept():
    model = load_robot("workcell")
    opt = TrajectoryOptimizer(model, TrajoptConfig())
    cur = np.zeros((20, len(model.joint_names)))
    goals = np.full((20, 3, 3), np.nan)
    r = opt.solve(cur, goals, np.ones((20, 3), bool), 0.05)
    assert not r.ok and "NaN" in r.reason
    np.testing.assert_array_equal(r.q, cur)


def test_hand_arm_tracks_fingertips_and_the_prior_shapes_unconstrained_fingers():
    model = load_robot("hand_arm")
    demos = [generate_demo("assembly", s) for s in (1, 2)]
    mean, std = hand_pose_prior(demos)
    assert 0.0 <= mean["index_j2"] < 1.6 and std["index_j2"] >= 0.05
    cfg = TrajoptConfig(point_map=dict(HAND_MAP), pose_mean=mean, pose_std=std, pose_weight=1e-6,
                        sphere_radius=0.005, max_iterations=5)
    opt = TrajectoryOptimizer(model, cfg)
    K, n = cfg.knots, len(model.joint_names)
    q0 = np.zeros(n)
    q0[1], q0[2] = -1.2, 1.5
    rng = np.random.default_rng(0)
    target = q0 + rng.normal(0, 0.1, n) * (np.arange(n) < 6)
    goals = np.repeat(opt.points(target)[None], K, 0)
    cur = np.repeat(q0[None], K, 0)
    for _ in range(30):
        r = opt.solve(cur, goals, np.ones((K, len(HAND_MAP)), bool), 0.05)
        cur = np.concatenate([r.q[1:], r.q[-1:]])
    err = np.linalg.norm(opt.points(r.q[-1]) - goals[-1], axis=1)
    assert err.max() < 0.01
    ring = model.joint_names.index("ring_j1")  # no goal on the ring finger: the prior decides its pose
    assert abs(r.q[-1][ring] - mean["ring_j1"]) < 0.05
