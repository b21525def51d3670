"""contactopt: contact models, the zero gradient of hard contacts, consistency losses, Gauss-Newton."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from contactopt import geometry as geo
from contactopt import losses
from contactopt.objective import Objective, flat_params, residual_fn
from contactopt.optim import GaussNewton
from contactopt.policy import Policy
from contactopt.sim import Step, World, fingertips, simulated_forces
from contactopt.tasks import get_task

torch.set_num_threads(1)
F64 = torch.float64
CUBE = get_task("turn_cube")
CYL = get_task("turn_cylinder")
WORLD = World()


def t(*x: float) -> torch.Tensor:
    return torch.tensor(x, dtype=F64)


def tip_at(x: float) -> torch.Tensor:
    """(1, 2, 2) fingertips: one on the +x side at x, the other far away."""
    return torch.tensor([[[x, 0.0], [1.0, 1.0]]], dtype=F64)


def forces(model: str, x: float, world: World = WORLD) -> torch.Tensor:
    z = torch.zeros(1, dtype=F64)
    f, _, _ = simulated_forces(tip_at(x), torch.zeros(1, 2, 2, dtype=F64), torch.zeros(1, 2, dtype=F64), z,
                               torch.zeros(1, 2, dtype=F64), z, CYL, world, model)
    return f[0, 0]


def test_box_signed_distance_and_normal() -> None:
    d, n = geo.sdf_box(t(0.05, 0.0)[None], t(0.0, 0.0)[None], t(0.0), 0.03)
    assert float(d) == pytest.approx(0.02, abs=1e-6)
    assert n[0].tolist() == pytest.approx([1.0, 0.0], abs=1e-6)
    d, n = geo.sdf_box(t(0.0, 0.05)[None], t(0.0, 0.0)[None], t(math.pi / 2), 0.03)  # rotated
    assert float(d) == pytest.approx(0.02, abs=1e-6)
    assert n[0].tolist() == pytest.approx([0.0, 1.0], abs=1e-6)
    d, _ = geo.sdf_box(t(0.02, 0.0)[None], t(0.0, 0.0)[None], t(0.0), 0.03)  # inside
    assert float(d) == pytest.approx(-0.01, abs=1e-6)


@pytest.mark.parametrize("pen", [0.001, 0.005])
def test_hard_and_softplus_normal_force_at_known_penetration(pen: float) -> None:
    x = CYL.size + WORLD.tip_radius - pen  # tip center penetrating the cylinder by pen
    hard = forces("hard", x)
    assert hard.tolist() == pytest.approx([-WORLD.stiffness * pen, 0.0], rel=1e-4, abs=1e-9)
    c = WORLD.smoothness
    soft = forces("softplus", x)
    expected = WORLD.stiffness * c * math.log1p(math.exp(pen / c))  # Eq. 2.1 with d = -pen
    assert float(-soft[0]) == pytest.approx(expected, rel=1e-4)
    assert float(-soft[0]) > float(-hard[0])  # the softplus lies above the ramp


def test_softplus_approaches_hard_for_small_smoothness() -> None:
    x = CYL.size + WORLD.tip_radius - 0.004
    sharp = replace(WORLD, smoothness=1e-5)
    assert float(forces("softplus", x, sharp)[0]) == pytest.approx(float(forces("hard", x)[0]), rel=1e-3)


def test_separated_contact_hard_zero_softplus_positive() -> None:
    x = CYL.size + WORLD.tip_radius + 0.01  # 1 cm apart
    assert forces("hard", x).abs().max() == 0.0
    assert float(-forces("softplus", x)[0]) > 0.0


def test_friction_stays_inside_the_cone() -> None:
    x = CYL.size + WORLD.tip_radius - 0.002
    z = torch.zeros(1, dtype=F64)
    tip_vel = torch.tensor([[[0.0, 1.0], [0.0, 0.0]]], dtype=F64)  # sliding along the surface
    f, _, _ = simulated_forces(tip_at(x), tip_vel, torch.zeros(1, 2, dtype=F64), z,
                               torch.zeros(1, 2, dtype=F64), z, CYL, WORLD, "hard")
    fn, ft = -float(f[0, 0, 0]), float(f[0, 0, 1])
    assert ft > 0 and ft == pytest.approx(WORLD.friction_mu * fn, rel=1e-6)


def task_gradient(model: str) -> torch.Tensor:
    torch.manual_seed(0)
    policy = Policy(contacts=False)
    task = replace(CUBE, steps=4)
    fn = residual_fn(policy, Objective(task, model=model), torch.zeros(4, 2, dtype=F64))
    w, _ = flat_params(policy)
    w.requires_grad_(True)
    r = fn(w)
    (g,) = torch.autograd.grad(r @ r, w)
    return g


def test_hard_contact_policy_gradient_is_zero_softplus_is_not() -> None:
    tips = fingertips(torch.tensor([WORLD.q0], dtype=F64), WORLD)
    assert (tips[0, :, 0].abs() - CUBE.size - WORLD.tip_radius).min() > 0.005  # fingers start apart
    assert task_gradient("hard").abs().max() == 0.0
    assert task_gradient("softplus").abs().max() > 1e-8


def step(p_a, p_b, force, tip_vel=((0.0, 0.0), (0.0, 0.0)), tips=((-0.04, 0.0), (0.04, 0.0))) -> Step:
    def b(x):
        return torch.tensor([x], dtype=F64)
    return Step(b(tips), b(tip_vel), b((0.0, 0.0)), b(0.0), b((0.0, 0.0)), b(0.0), b(p_a), b(p_b), b(force))


def test_shape_loss_zero_inside_positive_outside() -> None:
    inside = step(((-0.04, 0.0), (0.04, 0.0)), ((-0.02, 0.0), (0.02, 0.0)), ((0, 0), (0, 0)))
    assert losses.shape_residual(inside, CUBE, WORLD).abs().max() == 0.0
    out = step(((-0.04, 0.0), (0.04, 0.0)), ((-0.05, 0.0), (0.02, 0.0)), ((0, 0), (0, 0)))
    r = losses.shape_residual(out, CUBE, WORLD)
    assert float(r.max()) == pytest.approx(0.02, abs=1e-9)  # 2 cm beyond the cube's -x face


def test_distance_force_complementarity() -> None:
    s = step(((-0.04, 0.0), (0.04, 0.0)), ((-0.03, 0.02), (0.04, 0.0)), ((2.0, 0.0), (0.0, 0.0)))
    r = losses.distance_residual(s)
    assert r[0, 0, :2].tolist() == pytest.approx([2.0 * -0.01, 0.0])
    assert float(r[0, 0, 2]) == pytest.approx(2.0 * math.hypot(0.01, 0.02))
    assert r[0, 1].abs().max() < 1e-9  # no force, no gap (norms are smoothed at zero)
    perpendicular = step(((-0.04, 0.0), (0.04, 0.0)), ((-0.04, 0.01), (0.04, 0.0)), ((2.0, 0.0), (0.0, 0.0)))
    r = losses.distance_residual(perpendicular)
    assert r[0, 0, :2].abs().max() == 0.0 and float(r[0, 0, 2]) == pytest.approx(0.02)


def test_friction_cone_loss() -> None:
    _, n = losses.contact_normal(step(((0, 0),) * 2, ((0, 0),) * 2, ((0, 0),) * 2), CUBE)
    pushing = step(((0, 0),) * 2, ((0, 0),) * 2, ((1.0, 0.5), (-1.0, 0.0)))  # inside the cone (mu 0.8)
    assert losses.friction_residual(pushing, n, WORLD).abs().max() == 0.0
    sideways = step(((0, 0),) * 2, ((0, 0),) * 2, ((1.0, 2.0), (-1.0, 0.0)))
    assert float(losses.friction_residual(sideways, n, WORLD)[0, 0].max()) == pytest.approx(2.0 - 0.8, rel=1e-4)
    pulling = step(((0, 0),) * 2, ((0, 0),) * 2, ((-1.0, 0.0), (-1.0, 0.0)))
    assert float(losses.friction_residual(pulling, n, WORLD)[0, 0].max()) == pytest.approx(0.8, rel=1e-4)


def test_slippage_loss_tangential_only() -> None:
    pts = ((-0.035, 0.0), (0.035, 0.0))
    sliding = step(pts, pts, ((1.0, 0.0), (0.0, 0.0)), tip_vel=((0.0, 0.1), (0.0, 0.0)))
    assert losses.slippage_residual(sliding, torch.tensor([[[-1.0, 0.0], [1.0, 0.0]]], dtype=F64))[
        0, 0].tolist() == pytest.approx([0.0, 0.0])  # force (1, 0) times v_t (0, 0.1) elementwise
    sliding2 = step(pts, pts, ((1.0, 1.0), (0.0, 0.0)), tip_vel=((0.0, 0.1), (0.0, 0.0)))
    assert losses.slippage_residual(sliding2, torch.tensor([[[-1.0, 0.0], [1.0, 0.0]]], dtype=F64))[
        0, 0].tolist() == pytest.approx([0.0, 0.1])
    pressing = step(pts, pts, ((1.0, 1.0), (0.0, 0.0)), tip_vel=((0.1, 0.0), (0.0, 0.0)))
    assert losses.slippage_residual(pressing, torch.tensor([[[-1.0, 0.0], [1.0, 0.0]]], dtype=F64)).abs(
    ).max() == 0.0


def test_intersection_loss_is_the_penetration_depth() -> None:
    d_obj = torch.tensor([[WORLD.tip_radius - 0.002, WORLD.tip_radius + 0.01]], dtype=F64)
    assert losses.intersection_residual(d_obj, WORLD)[0].tolist() == pytest.approx([0.002, 0.0])


def test_gauss_newton_step_reduces_loss_on_a_tiny_rollout() -> None:
    torch.manual_seed(0)
    policy = Policy(hidden=8)
    task = replace(CUBE, steps=3)
    obj = Objective(task)
    pos = torch.zeros(2, 2, dtype=F64)
    fn = residual_fn(policy, obj, pos)
    w, _ = flat_params(policy)
    before = float(fn(w) @ fn(w))
    gn = GaussNewton(cg_iters=20)
    w2, after = gn.step(fn, w)
    assert after < before
    assert float(fn(w2) @ fn(w2)) == pytest.approx(after)


def test_gauss_newton_solves_a_nonlinear_least_squares_problem() -> None:
    def rosenbrock(w: torch.Tensor) -> torch.Tensor:
        return torch.stack([10 * (w[1] - w[0] ** 2), 1 - w[0]])
    w = torch.tensor([-1.2, 1.0], dtype=F64)
    gn = GaussNewton(lam=1e-3, cg_iters=2, cg_tol=1e-12)
    for _ in range(20):
        w, _ = gn.step(rosenbrock, w)
    assert w.tolist() == pytest.approx([1.0, 1.0], abs=1e-6)


def test_nonfinite_residual_is_rejected_and_counted() -> None:
    gn = GaussNewton()
    w = torch.tensor([1.0], dtype=F64)
    w2, loss = gn.step(lambda v: v * float("nan"), w)
    assert torch.equal(w2, w) and math.isnan(loss)
    assert gn.counters["nonfinite"] == 1


def test_unknown_task_lists_the_tasks() -> None:
    with pytest.raises(ValueError, match="turn_cube"):
        get_task("spin")
