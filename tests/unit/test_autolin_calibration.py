"""autolin's GN-CG solver on the camera calibration's bundle adjustment (calibration/bundle.py's
residuals, detections of the simulated rig), against scipy's least_squares on the calibration's
own residual function."""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

from bench._autolin_calibration import make_problem
from calibration.bundle import Problem
from shared.autolin import camera as C
from shared.autolin.solver import LeastSquares

SIZE = (640, 480)


def calibration_problem(frames: int = 20) -> tuple[Problem, np.ndarray, C.CameraProblem]:
    return make_problem(frames, seed=0, noise_px=0.1)


def to_x(prob: Problem, params: list[np.ndarray]) -> np.ndarray:
    """autolin's parameter arrays as calibration/bundle.py's unknowns."""
    intr, ext, boards = C.to_rotation_vectors(params)
    return np.concatenate([intr[:, prob.free].ravel(), ext[prob.movable].ravel(), boards.ravel()])


def test_gn_cg_reaches_scipy_cost_on_the_calibration_bundle_adjustment():
    prob, x0, cp = calibration_problem()
    mask = np.ones(len(prob.obs.cam), bool)
    ls = LeastSquares(C.reprojection, C.PARAM_TYPES, C.DATA_TYPES, cp.index)
    r, _ = ls.residuals(cp.params, cp.data)
    np.testing.assert_allclose(np.stack(r, 1).ravel(), prob.residuals(x0, mask), atol=1e-9)  # same residuals
    np.testing.assert_allclose(to_x(prob, cp.params), x0, atol=1e-12)  # and the same unknowns
    ref = least_squares(lambda x: prob.residuals(x, mask), x0, method="trf", x_scale="jac")
    res = ls.solve(cp.params, cp.data, fixed=cp.fixed)
    assert res.costs[0] > 5 * res.cost  # the start is far from the optimum
    assert res.cost <= ref.cost * (1 + 1e-9)
    # the solution, read back into the calibration's unknowns, has the cost the solver reports
    x = to_x(prob, res.params)
    assert abs(0.5 * np.sum(prob.residuals(x, mask) ** 2) - res.cost) < 1e-9 * res.cost
    np.testing.assert_array_equal(res.params[0][prob.ref], cp.params[0][prob.ref])  # the reference camera held
