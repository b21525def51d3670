"""Stretch-minimizing unwrap (thesis 4.5.4) and the angle-preserving LSCM it is compared with.

An angle-preserving (conformal) unwrap keeps shapes but not sizes, so a part cut from it is
stretched when glued onto the curved surface. This unwrap minimises the edge-length error instead,
by sequential least squares: each iteration first aligns every triangle's rest shape (its 3-D
triangle in its own plane) onto its current flat position with the Kabsch algorithm, rotations
only, so no triangle can be mirrored (edge lengths alone would allow flipped parts); then it solves
the linear least-squares problem that makes every edge vector equal its aligned rest edge (a sparse
system factorised once). Gaussian noise, decaying geometrically, is added to the flat positions
before each alignment to shake the solution out of local minima. LSCM (libigl) starts it.

Distortion is measured per edge (flat length / surface length - 1) and per face (flat area /
surface area). LSCM's scale is arbitrary (it pins two vertices), so before comparing, its layout is
scaled by the factor that best matches the surface's edge lengths (least squares): the most
favourable scale for it.
"""

from __future__ import annotations

from dataclasses import dataclass

import igl
import numpy as np
import scipy.sparse as sp
from scipy.optimize import least_squares
from scipy.sparse.linalg import factorized

from skin.errors import SkinError
from skin.mesh import check_sheet

EDGES = ((0, 1), (1, 2), (2, 0))


@dataclass
class Unwrap:
    """A flat layout (V,2) of a part and the loss (mean squared relative edge error) per iteration."""

    uv: np.ndarray
    loss: list[float]


def _rest_triangles(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Each triangle in its own plane (F,3,2): first vertex at the origin, first edge along x."""
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    e1, e2 = b - a, c - a
    x = e1 / np.maximum(np.linalg.norm(e1, axis=1, keepdims=True), 1e-12)
    n = np.cross(e1, e2)
    y = np.cross(n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12), x)
    out = np.zeros((len(f), 3, 2))
    out[:, 1, 0] = np.einsum("ij,ij->i", e1, x)
    out[:, 2] = np.stack([np.einsum("ij,ij->i", e2, x), np.einsum("ij,ij->i", e2, y)], axis=1)
    return out


def kabsch_2d(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Batched proper rotations (F,2,2) best turning centred point sets src (F,k,2) onto dst (F,k,2)."""
    H = np.einsum("fki,fkj->fij", src - src.mean(axis=1, keepdims=True), dst - dst.mean(axis=1, keepdims=True))
    # In 2-D the best rotation angle has a closed form; it never reflects.
    ang = np.arctan2(H[:, 0, 1] - H[:, 1, 0], H[:, 0, 0] + H[:, 1, 1])
    c, s = np.cos(ang), np.sin(ang)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def signed_areas(uv: np.ndarray, f: np.ndarray) -> np.ndarray:
    e1, e2 = uv[f[:, 1]] - uv[f[:, 0]], uv[f[:, 2]] - uv[f[:, 0]]
    return 0.5 * (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])


def lscm(v: np.ndarray, f: np.ndarray, name: str = "part") -> np.ndarray:
    """Angle-preserving unwrap (libigl's least-squares conformal map), scaled to best match the
    surface's edge lengths and turned so its faces keep their winding."""
    loops = check_sheet(v, f, name)
    outline = loops[0]
    far = outline[np.argmax(np.linalg.norm(v[outline] - v[outline[0]], axis=1))]
    b = np.array([outline[0], far], np.int64)
    bc = np.array([[0.0, 0.0], [1.0, 0.0]])
    uv = np.asarray(igl.lscm(np.asarray(v, float), np.asarray(f, np.int64), b, bc)[0])
    if not np.isfinite(uv).all():
        raise SkinError("unwrap_failed", name, "LSCM produced non-finite coordinates")
    if signed_areas(uv, f).sum() < 0:
        uv[:, 1] = -uv[:, 1]
    return uv * best_scale(v, uv, f)


def best_scale(v: np.ndarray, uv: np.ndarray, f: np.ndarray) -> float:
    """The factor s minimising sum (s l_flat - l_surface)^2 over the edges."""
    l3, l2 = _edge_lengths(v, f), _edge_lengths(uv, f)
    return float((l2 @ l3) / max(l2 @ l2, 1e-18))


def _edge_lengths(x: np.ndarray, f: np.ndarray) -> np.ndarray:
    e = np.concatenate([f[:, [i, j]] for i, j in EDGES])
    return np.linalg.norm(x[e[:, 1]] - x[e[:, 0]], axis=1)


def stretch_minimizing(v: np.ndarray, f: np.ndarray, name: str = "part", iterations: int = 150,
                       refine: int = 100, noise: float = 0.05, decay: float = 0.95, align: float = 0.01,
                       robust: float | None = 1e-2, seed: int = 0) -> Unwrap:
    """Unwrap a part (V,3) / (F,3) with the least edge-length error. Raises SkinError naming the part
    on bad topology.

    Phase 1, ``iterations`` rounds: noise (``noise`` x the mean edge length, times ``decay`` per
    round, none in the last fifth), Kabsch alignment of every triangle, then the linear least squares
    of the aligned edge vectors. Phase 2, at most ``refine`` least-squares steps on the relative edge-length
    residuals themselves, with the Kabsch-aligned edge vectors kept as a weak (``align``) second set
    of residuals, under a soft-L1 loss of scale ``robust`` (see ``_refine``)."""
    v, f = np.asarray(v, float), np.asarray(f, np.int64)
    uv = lscm(v, f, name)
    rest = _rest_triangles(v, f)
    nv = len(v)
    # Residual per face edge (i -> j): (x_j - x_i) - R_f (p_j - p_i); pin vertex 0 against drift.
    rows = np.arange(3 * len(f))
    ei = np.concatenate([f[:, i] for i, _ in EDGES])
    ej = np.concatenate([f[:, j] for _, j in EDGES])
    A = sp.csr_matrix((np.r_[-np.ones(len(rows)), np.ones(len(rows))], (np.r_[rows, rows], np.r_[ei, ej])),
                      shape=(len(rows), nv))
    L = (A.T @ A).tolil()
    L[0, 0] += 1.0
    solve = factorized(L.tocsc())
    AT = A.T.tocsr()
    rest_edges = np.concatenate([rest[:, j] - rest[:, i] for i, j in EDGES])  # (3F,2)
    l3 = np.linalg.norm(rest_edges, axis=1)
    sigma = noise * float(l3.mean())
    rng = np.random.default_rng(seed)
    quiet = int(0.8 * iterations)
    loss = []
    for it in range(iterations):
        cur = uv + (rng.normal(0.0, sigma, uv.shape) if it < quiet else 0.0)
        sigma *= decay
        R = kabsch_2d(rest, cur[f])
        target = np.einsum("fij,fj->fi", np.tile(R, (3, 1, 1)), rest_edges)
        rhs = AT @ target
        rhs[0] += uv[0]
        uv = np.stack([solve(rhs[:, 0]), solve(rhs[:, 1])], axis=1)
        loss.append(float(np.mean((np.linalg.norm(A @ uv, axis=1) / l3 - 1.0) ** 2)))
    uv = _refine(uv, f, A, rest, rest_edges, l3, refine, align, robust, loss)
    if not np.isfinite(uv).all():
        raise SkinError("unwrap_failed", name, "the unwrap diverged (degenerate triangles?)")
    return Unwrap(uv, loss)


def _refine(uv: np.ndarray, f: np.ndarray, A: sp.csr_matrix, rest: np.ndarray, rest_edges: np.ndarray,
            l3: np.ndarray, steps: int, align: float, robust: float | None, loss: list[float]) -> np.ndarray:
    """Trust-region least squares (scipy) on edge-length residuals (|d_e| - l_e) / l_e plus ``align``
    x the Kabsch residuals (d_e - R_f p_e) / l_e, under a soft-L1 loss of scale ``robust`` (the
    reported distortion is a mean absolute error); flat coordinates stacked [u..., v...]. Keeps the
    phase-1 layout if the result turns a face over. Appends the loss per evaluation to ``loss``."""
    A2 = sp.block_diag([A, A]).tocsr()  # A2 [u; v] = the (3F) u then v edge components
    Jalign = (sp.diags(np.tile(align / l3, 2)) @ A2).tocsr()

    def edges(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        d = (A2 @ x).reshape(2, -1).T
        return d, np.linalg.norm(d, axis=1)

    def fun(x: np.ndarray) -> np.ndarray:
        d, length = edges(x)
        R = kabsch_2d(rest, x.reshape(2, -1).T[f])
        target = np.einsum("fij,fj->fi", np.tile(R, (3, 1, 1)), rest_edges)
        loss.append(float(np.mean(((length - l3) / l3) ** 2)))
        return np.r_[(length - l3) / l3, align * ((d - target) / l3[:, None]).T.ravel()]

    def jac(x: np.ndarray) -> sp.csr_matrix:
        d, length = edges(x)
        g = d / (np.maximum(length, 1e-12) * l3)[:, None]
        return sp.vstack([sp.hstack([sp.diags(g[:, 0]) @ A, sp.diags(g[:, 1]) @ A]), Jalign]).tocsr()

    x0 = uv.T.ravel()
    res = least_squares(fun, x0, jac=jac, method="trf", loss="soft_l1" if robust else "linear",
                        f_scale=robust or 1.0, max_nfev=steps, x_scale="jac", tr_solver="lsmr")
    out = res.x.reshape(2, -1).T
    return out if (signed_areas(out, f) > 0).all() else uv


def distortion(v: np.ndarray, uv: np.ndarray, f: np.ndarray) -> dict[str, float | int]:
    """Per-face stretch of a flat layout: area ratio (flat / surface) and edge distortion (mean of
    |flat / surface length - 1| over a face's edges); min, max, mean of each; flipped faces."""
    f = np.asarray(f)
    per_face = face_edge_distortion(v, uv, f)
    a3 = np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1) / 2
    area = signed_areas(uv, f) / np.maximum(a3, 1e-18)
    edge = np.abs(_edge_lengths(uv, f) / np.maximum(_edge_lengths(v, f), 1e-18) - 1.0)
    return {"edge_mean": float(edge.mean()), "edge_max": float(edge.max()), "edge_min": float(edge.min()),
            "face_edge_mean": float(per_face.mean()), "face_edge_max": float(per_face.max()),
            "face_edge_min": float(per_face.min()), "area_mean": float(area.mean()), "area_min": float(area.min()),
            "area_max": float(area.max()), "flipped": int((area <= 0).sum()), "faces": len(f)}


def face_edge_distortion(v: np.ndarray, uv: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Per face (F,): mean |flat / surface length - 1| of its three edges."""
    r = _edge_lengths(uv, f) / np.maximum(_edge_lengths(v, f), 1e-18)
    return np.abs(r - 1.0).reshape(3, len(f)).mean(axis=0)
