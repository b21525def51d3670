"""A small synthetic bundle-adjustment problem (pinhole cameras as quaternion + translation,
3-D points, pixel observations), the solver's demonstration and test case, with the same
residuals in plain numpy for scipy's least_squares (rotation vectors as its parameters)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import ops as O
from .trace import Quat, Scalar, Vec3, dot

FOCAL = 500.0


def reprojection(q: Quat, t: Vec3, p: Vec3, u: Scalar, v: Scalar) -> tuple:
    """Pixel residual of point p seen by camera (q, t): focal * xy / z - observation."""
    c = q * p + t
    z = dot(c, [0.0, 0.0, 1.0])
    return FOCAL * dot(c, [1.0, 0.0, 0.0]) / z - u, FOCAL * dot(c, [0.0, 1.0, 0.0]) / z - v


@dataclass
class Problem:
    quats: np.ndarray      # (cams, 4) initial guess
    trans: np.ndarray      # (cams, 3)
    points: np.ndarray     # (points, 3)
    cam: np.ndarray        # (obs,) camera of each observation
    pt: np.ndarray         # (obs,) point of each observation
    uv: np.ndarray         # (obs, 2) observed pixels


def qexp(v: np.ndarray) -> np.ndarray:
    th = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.concatenate([np.cos(th / 2), np.sinc(th / (2 * np.pi)) / 2 * v], axis=-1)


def project(q: np.ndarray, t: np.ndarray, p: np.ndarray) -> np.ndarray:
    c = np.stack(O.qrot(tuple(q.T), tuple(p.T)), axis=1) + t
    return FOCAL * c[:, :2] / c[:, 2:]


def make_problem(n_cams: int = 6, n_points: int = 60, noise_px: float = 0.5, seed: int = 0) -> Problem:
    rng = np.random.default_rng(seed)
    q = qexp(rng.normal(scale=0.3, size=(n_cams, 3)))
    t = np.array([0.0, 0.0, 6.0]) + rng.normal(scale=0.3, size=(n_cams, 3))
    pts = rng.uniform(-1.5, 1.5, size=(n_points, 3))
    cam, pt = np.meshgrid(np.arange(n_cams), np.arange(n_points), indexing="ij")
    cam, pt = cam.ravel(), pt.ravel()
    uv = project(q[cam], t[cam], pts[pt]) + rng.normal(scale=noise_px, size=(cam.size, 2))
    q0 = np.stack([O.qmul(tuple(qexp(rng.normal(scale=0.03, size=3))), tuple(qi)) for qi in q])
    q0[0] = q[0]  # camera 0 is the gauge, held at its true pose
    t0 = t + rng.normal(scale=0.1, size=t.shape)
    t0[0] = t[0]
    return Problem(q0, t0, pts + rng.normal(scale=0.1, size=pts.shape), cam, pt, uv)


def numpy_residuals(x: np.ndarray, pr: Problem) -> np.ndarray:
    """The same residuals for scipy: x = rotation-vector steps and translations of cameras 1..,
    then the points; rotations are exp(step) q0 so both solvers share one parametrization."""
    n = pr.quats.shape[0] - 1
    rv, tt = x[:3 * n].reshape(n, 3), x[3 * n:6 * n].reshape(n, 3)
    q = np.concatenate([pr.quats[:1], np.stack([O.qmul(tuple(a), tuple(b)) for a, b in
                                                  zip(qexp(rv), pr.quats[1:], strict=True)])])
    t = np.concatenate([pr.trans[:1], tt])
    p = x[6 * n:].reshape(-1, 3)
    return (project(q[pr.cam], t[pr.cam], p[pr.pt]) - pr.uv).ravel()


def numpy_start(pr: Problem) -> np.ndarray:
    n = pr.quats.shape[0] - 1
    return np.concatenate([np.zeros(3 * n), pr.trans[1:].ravel(), pr.points.ravel()])
