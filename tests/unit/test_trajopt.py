"""The trajectory optimizer of thesis 7.4 on both robot models: tracking, limits, separating
planes between the arms, the hand-pose prior, and how bad input is refused."""

from __future__ import annotations

import numpy as np
import pytest

from services.trajopt.hand_prior import hand_pose_prior
from services.trajopt.optimizer import TrajectoryOptimizer, TrajoptConfig, TrajoptInputError
from services.world.teacher import generate_demo
from shared.kinematics import load_robot

K, DT = 20, 0.05


@pytest.fixture(scope="module")
def workcell():
    model = load_robot("workcell")
    return model, TrajectoryOptimizer(model, TrajoptConfig())


def home(left_y: float = 0.15, right_y: float = -0.15, z: float = 0.15) -> np.ndarray:
    """Joint vector with the carriages at world y = left_y, right_y (joints count from +-0.15)."""
    q = np.zeros(10)
    q[[4, 5]] = 0.01  # fingers a little open: plans keep 3 mm inside the joint limits
    q[[1, 7]] = left_y - 0.15, right_y + 0.15
    q[[2, 8]] = z
    return q


def at_rest(opt, q0):
    """The optimizer reset and the robot standing at q0: the executing trajectory and goals where it is."""
    opt.reset()
    return np.repeat(q0[None], K, 0), np.repeat(opt.points(q0)[None], K, 0)


def run(opt, cur, goals, mask, steps):
    results = []
    for _ in range(steps):
        r = opt.solve(cur, goals, mask, DT)
        results.append(r)
        cur = np.concatenate([r.q[1:], r.q[-1:]])  # receding horizon: shift by one knot
    return results


def check_limits(model, q, opt):
    assert np.all(q >= model.lower - 1e-6) and np.all(q <= model.upper + 1e-6)
    act = q[:, opt.act_index]
    vel = np.diff(act, axis=0) / DT
    assert np.all(np.abs(vel) <= opt.vmax_a + 1e-4)
    acc = np.diff(act, 2, axis=0) / DT ** 2
    assert np.all(np.abs(acc) <= opt.amax_a + 1e-2)


def test_tracks_moving_reachable_goals_within_joint_velocity_and_acceleration_limits(workcell):
    model, opt = workcell
    opt.reset()
    q0 = home()
    cur = np.repeat(q0[None], K, 0)
    base = opt.points(q0)
    errors = []
    for step in range(25):
        t = (step + np.arange(K)) * DT
        wobble = np.stack([0.05 * np.sin(t), 0.04 * np.cos(0.7 * t), -0.03 + 0.02 * np.sin(1.3 * t)], -1)
        goals = base[None] + wobble[:, None]
        r = opt.solve(cur, goals, np.ones((K, 3), bool), DT)
        assert r.ok, r.reason
        check_limits(model, r.q, opt)
        np.testing.assert_array_equal(r.q[:2], cur[:2])  # the fixed knots are the executing ones
        assert np.allclose(r.q[:, 5], r.q[:, 4])  # finger_b mimics finger_a
        errors.append(np.linalg.norm(opt.points(r.q[-1]) - goals[-1], axis=1).max())
        cur = np.concatenate([r.q[1:], r.q[-1:]])
    assert max(errors[5:]) < 1e-3


def test_a_goal_step_is_followed_at_the_velocity_limit(workcell):
    model, opt = workcell
    q0 = home()
    cur, goals = at_rest(opt, q0)
    goals[:, 2, 0] += 0.2  # right finger: 20 cm forward at once
    r = run(opt, cur, goals, np.ones((K, 3), bool), 1)[0]
    assert r.ok
    check_limits(model, r.q, opt)
    vx = np.diff(r.q[:, 6]) / DT
    assert vx.max() == pytest.approx(0.5, abs=1e-3)  # saturates the X axis, never exceeds it


def test_separating_planes_keep_the_arms_apart_when_goals_would_make_them_collide(workcell):
    model, opt = workcell
    q0 = home(left_y=0.05)
    cur, goals = at_rest(opt, q0)
    goals[:, 2] = [0.0, 0.04, 0.12]  # the right finger wants the left carriage's place
    results = run(opt, cur, goals, np.ones((K, 3), bool), 30)
    assert all(r.ok for r in results), [r.reason for r in results if not r.ok]
    q = results[-1].q
    z = q[opt.cfg.fixed_knots:, opt.act_index].ravel()[opt._expand]
    dist = opt.collision.witnesses(opt._link_poses(z), exact_below=np.inf).distance  # GJK/EPA everywhere
    assert dist.min() >= opt.cfg.margin - 1e-3
    poses = model.fk(q[-1])
    gap = poses["left_carriage"][1, 3] - poses["right_carriage"][1, 3]
    assert 0.08 + opt.cfg.margin - 1e-3 <= gap < 0.1  # pressed together, not overlapping
    # without the pairs the same goals drive the carriages into each other
    free = TrajectoryOptimizer(model, TrajoptConfig(collision_pairs=[]))
    q_free = run(free, np.repeat(q0[None], K, 0), goals, np.ones((K, 3), bool), 30)[-1].q[-1]
    poses = model.fk(q_free)
    assert poses["left_carriage"][1, 3] - poses["right_carriage"][1, 3] < 0.08


def test_the_next_cycle_reuses_the_planes_of_its_shifted_knots_exactly(workcell):
    """A cycle that starts from the last iterate shifted by whole knots takes its separating planes
    from the last final pass; they must equal a fresh GJK/EPA pass at those configurations."""
    model, opt = workcell
    q0 = home(left_y=0.05)
    cur, goals = at_rest(opt, q0)
    goals[:, 2] = [0.0, 0.04, 0.12]  # contact between the arms: slots in use
    F = opt.cfg.fixed_knots
    for shift in (1, 3, 0):
        r = opt.solve(cur, goals, np.ones((K, 3), bool), DT)
        assert r.ok, r.reason
        cur = np.concatenate([r.q[shift:], np.repeat(r.q[-1:], shift, 0)])
        z = cur[F:, opt.act_index].ravel()[opt._expand]
        reused = opt._shifted_planes(z)
        assert reused is not None, f"shift {shift} not recognized"
        fresh = opt._witness_vector(z, final=True)
        np.testing.assert_allclose(reused[0], fresh[0], atol=1e-12)
        np.testing.assert_array_equal(reused[1], fresh[1])
    moved = cur.copy()
    moved[F:, 0] += 1e-3  # anything but a shift of the last iterate computes planes afresh
    assert opt._shifted_planes(moved[F:, opt.act_index].ravel()[opt._expand]) is None


def test_buffered_calls_give_the_values_of_ordinary_calls(workcell):
    """solve() evaluates the SQP function, the final check and the QP through CasADi buffers wired
    into each other (H, gradient and G written into the QP's inputs): same values as plain calls."""
    import casadi as ca

    from services.trajopt.calls import BufferedFunction

    model, opt = workcell
    rng = np.random.default_rng(3)
    F, S = opt.cfg.fixed_knots, opt.slots
    z = np.tile(home()[opt.act_index], K - F) + 0.01 * rng.standard_normal(opt.nz)
    wit = opt._witness_vector(z)[0]
    params = (np.tile(home()[opt.act_index], F), rng.uniform(0, 0.3, opt._eval.nnz_in(2)),
              rng.uniform(0.5, 1, opt._eval.nnz_in(3)), DT, wit)
    assert S and np.abs(wit).max() > 0
    ref = [np.asarray(ca.DM(x).nonzeros()) for x in opt._eval(z, *params)]
    out = opt._lin(z, *params)
    for r, o in zip(ref, out, strict=True):
        np.testing.assert_array_equal(r, o)
    assert out[0] is opt._qp_in["h"] and out[3] is opt._qp_in["a"]  # no copy on the way to the QP
    g, cost = opt._check_call(z, *params)
    np.testing.assert_array_equal(g, ref[2])
    assert float(cost[0]) == float(ref[4][0])
    G = np.zeros((len(g), opt.nz))
    G[opt._G_rows, opt._G_cols] = ref[3]  # the (row, column) of each nonzero that solve() uses for G dz
    np.testing.assert_allclose(G, np.array(opt._eval(z, *params)[3]), rtol=0, atol=0)
    x = ca.SX.sym("x", 3)
    f = BufferedFunction(ca.Function("f", [x], [2 * x, ca.sumsqr(x)]))
    a, b = f(np.array([1.0, 2.0, 3.0]))
    assert a.tolist() == [2.0, 4.0, 6.0] and b.tolist() == [14.0]


def test_masked_goals_are_ignored_even_when_nan(workcell):
    _, opt = workcell
    q0 = home()
    cur, goals = at_rest(opt, q0)
    goals[:, 2] = np.nan
    mask = np.ones((K, 3), bool)
    mask[:, 2] = False
    r = opt.solve(cur, goals, mask, DT)
    assert r.ok and np.isfinite(r.q).all()
    np.testing.assert_allclose(r.q[:, 6:], cur[:, 6:], atol=1e-3)  # nothing asks the right arm to move
    assert opt.solve(np.zeros((K, 10)), np.repeat(opt.points(np.zeros(10))[None], K, 0), mask, DT).ok  # q=0 is safe


@pytest.mark.parametrize("case", ["nan_goal", "nan_state", "unreachable", "bad_dt"])
def test_bad_input_keeps_the_executing_trajectory_and_says_why(workcell, case):
    _, opt = workcell
    q0 = home()
    cur = np.repeat(q0[None], K, 0)
    goals = np.repeat(opt.points(q0)[None], K, 0)
    dt = DT
    if case == "nan_goal":
        goals[7, 1] = np.nan
    elif case == "nan_state":
        cur[3, 2] = np.nan
    elif case == "unreachable":
        goals[10:, 0] = [0.0, 0.0, 0.6]  # above the gantry
    else:
        dt = 0.0
    r = opt.solve(cur, goals, np.ones((K, 3), bool), dt)
    assert not r.ok
    np.testing.assert_array_equal(r.q, cur)
    expected = {"nan_goal": ("bad_input", "left/8 at knot 7 is NaN"), "nan_state": ("bad_input", "NaN"),
                "unreachable": ("unreachable", "left/4 -> left_tip_a at knot 10"), "bad_dt": ("bad_input", "dt")}
    status, words = expected[case]
    assert r.status == status and words in r.reason


def test_an_executing_trajectory_in_collision_is_rejected_with_the_violated_pair(workcell):
    _, opt = workcell
    opt.reset()
    q0 = home(left_y=0.0, right_y=0.0)  # carriages inside each other: no step can separate them
    cur = np.repeat(q0[None], K, 0)
    r = opt.solve(cur, np.repeat(opt.points(q0)[None], K, 0), np.ones((K, 3), bool), DT)
    # the linearised separation cannot be met inside the trust region: ipqp stops at its iteration
    # limit (it does not detect infeasibility), and the reason names what the iterate violates
    assert not r.ok and r.status == "qp_failed" and "QP (ipqp) failed" in r.reason, r.reason
    assert "violates separation left_carriage-right_carriage" in r.reason and r.max_violation > 0.04
    np.testing.assert_array_equal(r.q, cur)


def test_a_failed_qp_is_rejected_and_not_read_as_convergence(workcell):
    """With error_on_fail=False a QP plugin that fails still returns a vector (ipqp stopped by its
    iteration limit returns a small, finite step): the SQP must not take it for a converged step."""
    model, good = workcell
    opt = TrajectoryOptimizer(model, TrajoptConfig(qp_options={"max_iter": 3}))  # ipqp cannot finish
    q0 = home()
    cur = np.repeat(q0[None], K, 0)
    goals = np.repeat(opt.points(q0)[None], K, 0)
    goals[:, 2, 0] += 0.05
    r = opt.solve(cur, goals, np.ones((K, 3), bool), DT)
    assert not r.ok and r.status == "qp_failed", (r.status, r.reason)
    assert "QP (ipqp) failed in SQP iteration 1: Maximum number of iterations reached" in r.reason
    np.testing.assert_array_equal(r.q, cur)  # the executing trajectory, unchanged
    good.reset()
    assert good.solve(cur, goals, np.ones((K, 3), bool), DT).ok  # the same problem is fine for a working QP


class _Node:
    """What TrajoptService uses of a runtime Node, without Zenoh."""

    def __init__(self) -> None:
        import logging

        from shared.runtime.node import Stats

        self.stats, self.log, self.health_extra = Stats(), logging.getLogger("test"), None
        self.status, self.message, self.published = "starting", "", []

    def output(self, port: str):
        return type("Pub", (), {"put": lambda _self, msg: self.published.append(msg)})()

    def input(self, *args) -> None:
        pass

    def set_status(self, status: str, message: str = "") -> None:
        self.status, self.message = status, message


def test_service_publishes_the_last_safe_trajectory_and_reports_a_failed_qp_in_health():
    import asyncio
    from types import SimpleNamespace

    from services.trajopt.mapping import PlanArrays
    from services.trajopt.service import TrajoptService

    node = _Node()
    svc = TrajoptService(node, TrajoptService.Params(robot="workcell"))
    q0 = home()
    svc.on_state(SimpleNamespace(name=svc.model.joint_names, position=q0))
    target = q0.copy()
    target[6] += 0.05  # right finger 5 cm forward
    points = svc.opt.points(target)
    svc.plan = PlanArrays(100.0, 0.1, svc.opt.point_names, np.repeat(points[None], 30, 0), np.ones((30, 3), bool))
    published = lambda: np.array([p.positions for p in node.published[-1].points])  # noqa: E731
    for t in (100.0, 100.1, 100.2):
        asyncio.run(svc.tick(t))
        assert svc.last_result.ok, svc.last_result.reason
    safe = published()
    assert np.abs(safe[-1] - q0).max() > 0.01  # it is moving towards the goal
    working = svc.opt
    svc.opt = TrajectoryOptimizer(svc.model, TrajoptConfig(max_iterations=3, qp_options={"max_iter": 3}))
    asyncio.run(svc.tick(100.3))  # 2 knots later: the QP fails
    shifted = np.concatenate([safe[2:], np.repeat(safe[-1:], 2, 0)])
    np.testing.assert_array_equal(published(), shifted)  # the last safe trajectory, where it is now
    health = svc._health()
    assert health["last_status"] == "qp_failed" and "QP (ipqp) failed" in health["reason"]
    assert node.status == "degraded" and "QP (ipqp) failed" in node.message
    assert node.stats.errors["solve_rejected"] == 1
    svc.opt = working
    asyncio.run(svc.tick(100.4))
    health = svc._health()
    assert health["last_status"] != "qp_failed" and node.status == "ok"
    assert health["last_rejection"]["status"] == "qp_failed" and health["last_rejection"]["t"] == 100.3


def test_wrong_shapes_raise(workcell):
    _, opt = workcell
    with pytest.raises(TrajoptInputError, match="shape"):
        opt.solve(np.zeros((K, 9)), np.zeros((K, 3, 3)), np.ones((K, 3), bool), DT)
    with pytest.raises(TrajoptInputError, match="goals"):
        opt.solve(np.zeros((K, 10)), np.zeros((K, 2, 3)), np.ones((K, 2), bool), DT)


@pytest.fixture(scope="module")
def prior():
    return hand_pose_prior([generate_demo("assembly", s) for s in (1, 2)])


def hand_start(names):
    q0 = np.zeros(len(names))
    q0[names.index("shoulder_lift")], q0[names.index("elbow")] = -0.8, 1.2
    return q0


def test_hand_arm_tracks_wrist_and_fingertips_with_coupled_fingers(prior):
    model = load_robot("hand_arm")
    mean, std = prior
    opt = TrajectoryOptimizer(model, TrajoptConfig(pose_mean=mean, pose_std=std, pose_weight=1e-6))
    names = model.joint_names
    q0 = hand_start(names)
    target = q0.copy()
    target[:6] += np.random.default_rng(0).normal(0, 0.1, 6)
    for finger in ("index", "middle", "ring", "thumb"):
        target[names.index(f"{finger}_j2")] = target[names.index(f"{finger}_j3")] = 0.6
    goals = np.repeat(opt.points(target)[None], K, 0)
    results = run(opt, np.repeat(q0[None], K, 0), goals, np.ones((K, 5), bool), 40)
    q = results[-1].q[-1]
    assert results[-1].ok
    assert np.linalg.norm(opt.points(q) - goals[-1], axis=1).max() < 5e-3
    for finger in ("index", "middle", "ring", "thumb"):  # the distal joint follows the middle one
        assert q[names.index(f"{finger}_j3")] == pytest.approx(q[names.index(f"{finger}_j2")])


def test_hand_pose_prior_decides_fingers_without_goals(prior):
    """Only the wrist has a goal: every finger joint settles at its prior mean (7.22); a coupled
    pair settles at the deviation-weighted mean of both joints' priors."""
    model = load_robot("hand_arm")
    mean, std = prior
    cfg = TrajoptConfig(pose_mean=mean, pose_std=std, pose_weight=1e-3,
                        point_weights={"right/4": 0.0, "right/8": 0.0, "right/12": 0.0, "right/16": 0.0})
    opt = TrajectoryOptimizer(model, cfg)
    names = model.joint_names
    q0 = hand_start(names)
    goals = np.repeat(opt.points(q0)[None], K, 0)
    q = run(opt, np.repeat(q0[None], K, 0), goals, np.ones((K, 5), bool), 40)[-1].q[-1]
    assert np.linalg.norm(opt.points(q)[0] - goals[-1, 0]) < 1e-3
    for finger in ("index", "middle", "ring"):
        j1 = names.index(f"{finger}_j1")
        assert abs(q[j1] - mean[f"{finger}_j1"]) < 0.02
        w2, w3 = std[f"{finger}_j2"] ** -2, std[f"{finger}_j3"] ** -2
        expected = (w2 * mean[f"{finger}_j2"] + w3 * mean[f"{finger}_j3"]) / (w2 + w3)
        assert abs(q[names.index(f"{finger}_j2")] - expected) < 0.02
    assert abs(q[names.index("ring_j1")] - q0[names.index("ring_j1")]) > 0.3  # it did move there
