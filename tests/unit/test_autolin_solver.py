"""autolin's Gauss-Newton + conjugate-gradient solver on a small bundle adjustment, against
scipy's least_squares on the same residuals."""

from __future__ import annotations

import numpy as np
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
    res = solve(pr, iterations=50)
    assert res.cost < 1e-12
    assert res.cg_iterations > res.iterations  # the inner loop did the work
