"""Global bundle adjustment over all cameras and observations (thesis 5.5).

Unknowns: per camera the intrinsics (fx, fy, cx, cy) with OpenCV's 5-coefficient distortion
(k1 k2 p1 p2 k3) and the pose ``cam_T_rig`` (the reference camera fixes the gauge: it is the rig
frame), and per frame set the board pose ``rig_T_board``. Residuals are pixel reprojection errors
of every kept chessboard corner, under a robust loss (soft L1, as ``scipy.optimize.least_squares``
defines it). The solver is Levenberg-Marquardt on the normal equations: with about a thousand
unknowns they are a small dense system, where ``least_squares``' sparse trust region (LSMR inner
solves) needed minutes for the same problem. The Jacobian is sparse (a residual depends on one
camera and one board pose) and taken by finite differences over at most 21 column groups that touch
disjoint rows, whatever the number of frame sets. Corners whose error exceeds a multiple of the
robust error scale are dropped and the problem is solved again.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.linalg import cho_factor, cho_solve
from scipy.sparse import csr_matrix

from calibration.detect import Detections
from calibration.init import Initial
from shared.charuco import BoardSpec

N_INTR = 9  # fx fy cx cy k1 k2 p1 p2 k3
# Camera models: which of the 9 intrinsics are unknowns. "full": all (OpenCV's default model);
# "centred": one focal length (fx = fy), k1 and k2, the principal point at the image centre and no
# tangential distortion (the model aniposelib fits; right for lenses centred on their sensor).
MODELS = {"full": (0, 1, 2, 3, 4, 5, 6, 7, 8), "centred": (0, 4, 5)}
OUTLIER_SIGMAS = 5.0  # of the robust error scale
MIN_OUTLIER_PX = 0.5  # never drop corners closer than this


@dataclass
class Observations:
    cam: np.ndarray  # (M,) camera index
    frame: np.ndarray  # (M,) index into the board poses
    obj: np.ndarray  # (M,3) board point
    uv: np.ndarray  # (M,2) detected pixel
    frames: list[int]  # board pose index -> frame set number
    ids: np.ndarray  # (M,) chessboard corner id


@dataclass
class BundleResult:
    K: list[np.ndarray]
    dist: list[np.ndarray]
    cam_T_rig: list[np.ndarray]
    rig_T_board: dict[int, np.ndarray]
    obs: Observations
    residuals: np.ndarray  # (M,2) final reprojection error per observation
    inlier: np.ndarray  # (M,) bool
    rms_px: list[float]  # per camera, over inliers
    iterations: int


def observations(det: Detections, board: BoardSpec, frames_with_pose: set[int]) -> Observations:
    obj_all = board.corners()
    frames = sorted(frames_with_pose & {v.frame for v in det.views})
    index = {f: i for i, f in enumerate(frames)}
    views = [v for v in det.views if v.frame in index]
    return Observations(
        np.concatenate([np.full(len(v.ids), v.camera) for v in views]),
        np.concatenate([np.full(len(v.ids), index[v.frame]) for v in views]),
        np.concatenate([obj_all[v.ids] for v in views]), np.concatenate([v.corners for v in views]), frames,
        np.concatenate([v.ids for v in views]))


def rotations(rvecs: np.ndarray) -> np.ndarray:
    """Rotation matrices (N,3,3) of rotation vectors (N,3) (Rodrigues' formula)."""
    theta = np.linalg.norm(rvecs, axis=1)
    small = theta < 1e-12
    k = rvecs / np.where(small, 1.0, theta)[:, None]
    zero = np.zeros(len(k))
    Kx = np.stack([zero, -k[:, 2], k[:, 1], k[:, 2], zero, -k[:, 0], -k[:, 1], k[:, 0], zero], 1).reshape(-1, 3, 3)
    s, c = np.sin(theta)[:, None, None], np.cos(theta)[:, None, None]
    return np.eye(3) + s * Kx + (1 - c) * (Kx @ Kx)


def project(intr: np.ndarray, p_cam: np.ndarray) -> np.ndarray:
    """OpenCV pinhole + 5-coefficient distortion; intr (M,9) per point."""
    fx, fy, cx, cy, k1, k2, p1, p2, k3 = intr.T
    x, y = p_cam[:, 0] / p_cam[:, 2], p_cam[:, 1] / p_cam[:, 2]
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([fx * xd + cx, fy * yd + cy], axis=1)


class Problem:
    def __init__(self, n_cams: int, reference: int, obs: Observations, model: str = "full") -> None:
        if model not in MODELS:
            raise ValueError(f"camera model must be one of {', '.join(MODELS)}, got {model!r}")
        self.n, self.ref, self.obs = n_cams, reference, obs
        self.free = np.array(MODELS[model])
        self.tied_aspect = 1 not in MODELS[model]  # fy follows fx
        self.n_intr = len(self.free)
        self.fixed = np.zeros((n_cams, N_INTR))  # values of the intrinsics that are not unknowns
        self.movable = [c for c in range(n_cams) if c != reference]
        self.ext_index = {c: i for i, c in enumerate(self.movable)}
        self.n_frames = len(obs.frames)
        self.o_ext = self.n_intr * n_cams
        self.o_board = self.o_ext + 6 * len(self.movable)
        self.size = self.o_board + 6 * self.n_frames

    def pack(self, K: list, dist: list, cam_T_rig: list, rig_T_board: dict) -> np.ndarray:
        x = np.zeros(self.size)
        for c in range(self.n):
            self.fixed[c] = [K[c][0, 0], K[c][1, 1], K[c][0, 2], K[c][1, 2], *dist[c]]
            x[self.n_intr * c:self.n_intr * (c + 1)] = self.fixed[c, self.free]
        for c, i in self.ext_index.items():
            x[self.o_ext + 6 * i:self.o_ext + 6 * i + 6] = _rt(cam_T_rig[c])
        for i, f in enumerate(self.obs.frames):
            x[self.o_board + 6 * i:self.o_board + 6 * i + 6] = _rt(rig_T_board[f])
        return x

    def intrinsics(self, x: np.ndarray) -> np.ndarray:
        """(n, 9) intrinsics: the unknowns where the model has them, the fixed values elsewhere."""
        intr = self.fixed.copy()
        intr[:, self.free] = x[:self.o_ext].reshape(self.n, self.n_intr)
        if self.tied_aspect:
            intr[:, 1] = intr[:, 0]
        return intr

    def unpack(self, x: np.ndarray) -> tuple[list, list, list, dict]:
        intr = self.intrinsics(x)
        K = [np.array([[i[0], 0, i[2]], [0, i[1], i[3]], [0, 0, 1.0]]) for i in intr]
        dist = [i[4:].copy() for i in intr]
        ext = self._extrinsics(x)
        cam_T_rig = [_T(e) for e in ext]
        boards = x[self.o_board:].reshape(-1, 6)
        return K, dist, cam_T_rig, {f: _T(boards[i]) for i, f in enumerate(self.obs.frames)}

    def _extrinsics(self, x: np.ndarray) -> np.ndarray:
        ext = np.zeros((self.n, 6))
        ext[self.movable] = x[self.o_ext:self.o_board].reshape(-1, 6)
        return ext

    def residuals(self, x: np.ndarray, mask: np.ndarray) -> np.ndarray:
        cam, frame, obj, uv = (a[mask] for a in (self.obs.cam, self.obs.frame, self.obs.obj, self.obs.uv))
        intr = self.intrinsics(x)
        ext = self._extrinsics(x)
        boards = x[self.o_board:].reshape(-1, 6)
        p_rig = np.einsum("mij,mj->mi", rotations(boards[:, :3])[frame], obj) + boards[frame, 3:]
        p_cam = np.einsum("mij,mj->mi", rotations(ext[:, :3])[cam], p_rig) + ext[cam, 3:]
        return (project(intr[cam], p_cam) - uv).ravel()

    def jacobian(self, x: np.ndarray, mask: np.ndarray, r0: np.ndarray) -> csr_matrix:
        """Forward differences, one residual evaluation per column group: intrinsic k of every
        camera, extrinsic k of every movable camera, board coordinate k of every frame set."""
        cam, frame = self.obs.cam[mask], self.obs.frame[mask]
        m = len(cam)
        moving = cam != self.ref
        ext = np.array([self.ext_index.get(c, 0) for c in cam], int)
        ni = self.n_intr
        groups = [(ni * np.arange(self.n) + k, ni * cam + k, np.ones(m, bool)) for k in range(ni)]
        groups += [(self.o_ext + 6 * np.arange(len(self.movable)) + k, self.o_ext + 6 * ext + k, moving)
                   for k in range(6)]
        groups += [(self.o_board + 6 * np.arange(self.n_frames) + k, self.o_board + 6 * frame + k, np.ones(m, bool))
                    for k in range(6)]
        rows, cols, vals = [], [], []
        for group_cols, row_col, valid in groups:
            if len(group_cols) == 0:
                continue
            h = 1e-7 * np.maximum(np.abs(x[group_cols]), 1.0)
            xp = x.copy()
            xp[group_cols] += h
            step = np.zeros(self.size)
            step[group_cols] = h
            d = ((self.residuals(xp, mask) - r0).reshape(m, 2) / step[row_col][:, None])[valid]
            idx = np.flatnonzero(valid)
            rows += [2 * idx, 2 * idx + 1]
            cols += [row_col[valid], row_col[valid]]
            vals += [d[:, 0], d[:, 1]]
        return csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                          shape=(2 * m, self.size))


def _rt(T: np.ndarray) -> np.ndarray:
    return np.concatenate([cv2.Rodrigues(T[:3, :3])[0].ravel(), T[:3, 3]])


def _T(rt: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.asarray(rt[:3], float))[0]
    T[:3, 3] = rt[3:]
    return T


def robust_scale(err: np.ndarray) -> float:
    """Per-axis sigma from the median 2-D error norm (Rayleigh: median = 1.177 sigma)."""
    return float(np.median(err) / 1.1774) if len(err) else 0.0


def soft_l1_weights(r: np.ndarray, f_scale: float) -> np.ndarray:
    """IRLS weights of rho(z) = 2 (sqrt(1 + z) - 1), z = (r / f_scale)^2: rho'(z) = 1 / sqrt(1 + z)."""
    return 1.0 / np.sqrt(1.0 + (r / f_scale) ** 2)


def soft_l1_cost(r: np.ndarray, f_scale: float) -> float:
    return float(f_scale**2 * np.sum(np.sqrt(1.0 + (r / f_scale) ** 2) - 1.0))


def schur_solve(A: np.ndarray, g: np.ndarray, nc: int) -> np.ndarray:
    """Solve A x = g where A's trailing block (the board poses) is 6x6 block-diagonal: eliminate the
    boards (batched 6x6 inverses), solve the small camera system, substitute back."""
    nb = (len(g) - nc) // 6
    idx = nc + np.arange(nb * 6).reshape(nb, 6)
    Abb = A[idx[:, :, None], idx[:, None, :]]  # (nb,6,6)
    Abb_inv = np.linalg.inv(Abb)
    Acb = A[:nc, nc:].reshape(nc, nb, 6)
    AcbAinv = np.einsum("cfi,fij->cfj", Acb, Abb_inv)
    S = A[:nc, :nc] - np.einsum("cfj,dfj->cd", AcbAinv, Acb)
    gb = g[nc:].reshape(nb, 6)
    xc = cho_solve(cho_factor(S), g[:nc] - np.einsum("cfj,fj->c", AcbAinv, gb))
    xb = np.einsum("fij,fj->fi", Abb_inv, gb - np.einsum("cfi,c->fi", Acb, xc))
    return np.concatenate([xc, xb.ravel()])


def levenberg_marquardt(prob: Problem, x: np.ndarray, mask: np.ndarray, f_scale: float, max_iter: int = 50,
                        tol: float = 1e-10) -> tuple[np.ndarray, int]:
    """Minimise the soft-L1 cost of the masked residuals; (x, iterations)."""
    lam = 1e-3
    r = prob.residuals(x, mask)
    cost = soft_l1_cost(r, f_scale)
    for it in range(1, max_iter + 1):
        J = prob.jacobian(x, mask, r)
        w = soft_l1_weights(r, f_scale)
        JW = J.multiply(w[:, None]).tocsr()
        A = (JW.T @ J).toarray()
        g = JW.T @ r
        diag = np.maximum(np.diag(A), 1e-12)
        while True:
            try:
                step = -schur_solve(A + lam * np.diag(diag), g, prob.o_board)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            x_new = x + step
            r_new = prob.residuals(x_new, mask)
            cost_new = soft_l1_cost(r_new, f_scale)
            if cost_new < cost:
                lam = max(lam / 3, 1e-9)
                break
            lam *= 4
            if lam > 1e8:
                return x, it
        converged = cost - cost_new < tol * cost or np.max(np.abs(step)) < 1e-12
        x, r, cost = x_new, r_new, cost_new
        if converged:
            return x, it
    return x, max_iter


def bundle_adjust(det: Detections, board: BoardSpec, init: Initial, rounds: int = 2, model: str = "full"
                  ) -> BundleResult:
    obs = observations(det, board, set(init.rig_T_board))
    prob = Problem(len(det.names), init.reference, obs, model)
    x = prob.pack(init.K, init.dist, init.cam_T_rig, init.rig_T_board)
    mask = np.ones(len(obs.cam), bool)
    f_scale = 1.0
    iterations = 0
    for r in range(rounds):
        x, its = levenberg_marquardt(prob, x, mask, f_scale)
        iterations += its
        err = np.linalg.norm(prob.residuals(x, np.ones_like(mask)).reshape(-1, 2), axis=1)
        sigma = robust_scale(err[mask])
        if r < rounds - 1:
            mask = err < max(OUTLIER_SIGMAS * sigma, MIN_OUTLIER_PX)
            f_scale = max(3 * sigma, 0.05)
    res = prob.residuals(x, np.ones_like(mask)).reshape(-1, 2)
    K, dist, cam_T_rig, rig_T_board = prob.unpack(x)
    rms = []
    for c in range(prob.n):
        sel = mask & (obs.cam == c)
        rms.append(float(np.sqrt(np.mean(np.sum(res[sel] ** 2, axis=1)))) if sel.any() else float("nan"))
    return BundleResult(K, dist, cam_T_rig, rig_T_board, obs, res, mask, rms, iterations)
