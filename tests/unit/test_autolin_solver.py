"""autolin's Gauss-Newton + conjugate-gradient solver on a small bundle adjustment, against
scipy's least_squares on the same residuals."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares

from shared.autolin.bundle import make_problem, numpy_residuals, numpy_start, reprojection
from shared.autolin.solver import LeastSquares


def solve(pr, **kw):
    ls = LeastSquares(reprojection, ["quat", "vec3", "vec3"], ["scalar", "scalar"], [pr.cam, pr.cam, pr.pt])
    fixed = [np.arange(len(pr.quats)) == 0, np.arange(len(pr.trans)) == 0, None]
    return ls.solve([pr.quats, pr.trans, pr.points], [pr.uv[:, 0], pr.uv[:, 1]], fixed=fixed, **kw)


def test_gauss_newton_cg_reaches_scipy_cost_on_bundle_adjustment():
    pr = make_problem(n_cams=4, n_points=15, noise_px=0.5, seed=1)
    res = solve(pr)
    ref = least_squares(numpy_residuals, numpy_start(pr), args=(pr,), method="trf", x_scale="jac")
    assert res.costs[0] > 100 * res.cost  # it moved far from the start
    assert res.cost <= ref.cost * (1 + 1e-6)
    np.testing.assert_allclose(np.linalg.norm(res.params[0], axis=1), 1.0, rtol=1e-12)  # still unit quaternions
    np.testing.assert_array_equal(res.params[0][0], pr.quats[0])  # the gauge camera held


def test_noise_free_problem_is_solved_to_zero_residual():
    pr = make_problem(n_cams=3, n_points=15, noise_px=0.0, seed=2)
    runs = {pc: solve(pr, iterations=50, preconditioner=pc) for pc in ("schur-jacobi", "auto")}
    assert all(r.cost < 1e-12 for r in runs.values())
    res = runs["schur-jacobi"]
    assert res.cg_iterations > res.iterations  # matrix-free: the inner loop did the work


def dense_jacobian(ls, L, shapes, data):
    """J column by column through the forward program (unit input gradients)."""
    cols = []
    for j, s in enumerate(shapes):
        for k in range(int(np.prod(s))):
            v = [np.zeros(sh) for sh in shapes]
            v[j].reshape(-1)[k] = 1.0
            cols.append(np.stack(ls._jv(L, v, data), 1).ravel())
    return np.stack(cols, 1)


def test_diagonal_regularization_is_the_diagonal_of_jtj():
    pr = make_problem(n_cams=3, n_points=6, noise_px=0.5, seed=3)
    ls = LeastSquares(reprojection, ["quat", "vec3", "vec3"], ["scalar", "scalar"], [pr.cam, pr.cam, pr.pt])
    params, data = [pr.quats, pr.trans, pr.points], [pr.uv[:, 0], pr.uv[:, 1]]
    shapes = [(3, 3), (3, 3), (6, 3)]
    _, L = ls.residuals(params, data)
    J = dense_jacobian(ls, L, shapes, data)
    diag = np.concatenate([d.ravel() for d in ls.jtj_diagonal(L, shapes)])
    np.testing.assert_allclose(diag, np.sum(J * J, axis=0), rtol=1e-10)
    assert diag.max() / diag.min() > 10  # columns differ in scale: lambda I would damp them unevenly
    blocks = ls.jtj_blocks(L, shapes)  # a camera's pose block is J's columns of that camera
    cam1 = np.r_[3:6, 12:15]
    np.testing.assert_allclose(blocks[0][1], (J.T @ J)[np.ix_(cam1, cam1)], rtol=1e-10, atol=1e-9)


def test_both_regularizations_and_preconditioners_reach_scipy_cost():
    pr = make_problem(n_cams=4, n_points=15, noise_px=0.5, seed=1)
    ref = least_squares(numpy_residuals, numpy_start(pr), args=(pr,), method="trf", x_scale="jac")
    runs = {(reg, pc): solve(pr, regularization=reg, preconditioner=pc)
            for reg in ("diagonal", "identity") for pc in ("schur-jacobi", "schur")}
    for key, res in runs.items():
        assert res.cost <= ref.cost * (1 + 1e-9), key
    # the complete Schur complement as preconditioner: CG converges in a step or two
    assert runs["diagonal", "schur"].cg_iterations <= 2 * runs["diagonal", "schur"].iterations
    assert runs["diagonal", "schur-jacobi"].cg_iterations > runs["diagonal", "schur"].cg_iterations
    # the default takes the complete complement here: 3 kept cameras, 18 unknowns
    auto = solve(pr)
    assert (auto.cost, auto.cg_iterations) == (runs["diagonal", "schur"].cost, runs["diagonal", "schur"].cg_iterations)
    with pytest.raises(ValueError, match="regularization"):
        solve(pr, regularization="trust")
    with pytest.raises(ValueError, match="preconditioner"):
        solve(pr, preconditioner="ilu")
