"""Consistency constraints at inference (thesis 7.3-7.5, 7.8-7.10, 7.15) as least squares, pure numpy.

Every step, the next positions P minimize

    sum_i |(P_i - P_prev,i)/dt - V_i|^2                                  (7.5, every point)
  + w_pair sum_jk |(P_j - P_k - P_jk) eps / (|P_jk|^2 + eps)|^2 * dt^-2  (7.8, anchor pairs)

with object velocities first reconciled with the dynamics constraint (7.15)

    V_o = argmin |V_o - V_o,net|^2 + w_dyn |V_o - J_D V_pinch|^2

and the reservoir activations with 7.9-7.10: H = argmin w_H |H - H_P|^2 + |H - H_prev - dH_P dt|^2.

All constraints are linear in the unknowns; x, y and z share one normal matrix. Points that are
not anchors only carry 7.5, so their solution is the exact integral. The anchor system is
(A x A) with A = 12 + K: its constant part is precomputed and each step adds the pair weights to
a small dense matrix solved by Cholesky. Masked pairs (7.2.5) drop out of the sum.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import cho_factor, cho_solve

from services.policy.network import Layout


class ConsistencySolver:
    def __init__(self, layout: Layout, dt: float, w_pair: float = 1.0, w_dyn: float = 1.0,
                 pair_eps: float = 0.0025) -> None:
        self.layout, self.dt = layout, float(dt)
        self.w_pair, self.w_dyn, self.eps = float(w_pair), float(w_dyn), float(pair_eps)
        A = len(layout.anchors)
        # incidence of pair (j - k) on anchors: D (pairs x A); the normal matrix is
        # I/dt^2 + D^T W D, assembled as a weighted graph Laplacian.
        self.A = A
        self._eye = np.eye(A) / self.dt ** 2
        self._flat_jj = layout.pair_j * A + layout.pair_j
        self._flat_ii = layout.pair_i * A + layout.pair_i
        self._flat_ij = layout.pair_i * A + layout.pair_j
        self._flat_ji = layout.pair_j * A + layout.pair_i
        self._pinch = layout.pinch

    def velocities(self, v_hands: np.ndarray, v_objects: np.ndarray, J: np.ndarray | None) -> np.ndarray:
        """Reconciles object velocities with 7.15; returns all point velocities (P,3).
        v_hands (42,3), v_objects (K,3), J (K,2) or None."""
        if J is not None and self.w_dyn > 0:
            pinch = 0.5 * (v_hands[self._pinch[:, 0]] + v_hands[self._pinch[:, 1]])  # (2,3) pinch-point velocities
            v_objects = (v_objects + self.w_dyn * (J @ pinch)) / (1.0 + self.w_dyn)
        return np.concatenate([v_hands, v_objects], axis=0)

    def positions(self, prev: np.ndarray, vel: np.ndarray, pairs: np.ndarray | None = None,
                  pair_mask: np.ndarray | None = None) -> np.ndarray:
        """prev, vel (P,3); pairs (n_pairs,3) predicted next P_j - P_k (j > k) or None."""
        nxt = prev + vel * self.dt  # 7.5 alone: exact
        if pairs is None or self.w_pair <= 0:
            return nxt
        lay = self.layout
        # 7.8's normalization times eps^2: at contact a pair weighs w_pair position constraints
        w = self.w_pair * (self.eps / (np.einsum("ij,ij->i", pairs, pairs) + self.eps)) ** 2 / self.dt ** 2
        if pair_mask is not None:
            w = w * pair_mask
        N = self._eye.copy().ravel()
        np.add.at(N, self._flat_jj, w)
        np.add.at(N, self._flat_ii, w)
        np.add.at(N, self._flat_ij, -w)
        np.add.at(N, self._flat_ji, -w)
        N = N.reshape(self.A, self.A)
        wp = w[:, None] * pairs
        rhs = nxt[lay.anchors] / self.dt ** 2
        np.add.at(rhs, lay.pair_j, wp)
        np.add.at(rhs, lay.pair_i, -wp)
        nxt[lay.anchors] = cho_solve(cho_factor(N, check_finite=False), rhs, check_finite=False)
        return nxt

    @staticmethod
    def memory(H_pred: np.ndarray, H_prev: np.ndarray, dH: np.ndarray, dt: float, w_pred: float = 1.0) -> np.ndarray:
        """7.9 (weight ``w_pred``) + 7.10 (weight 1) as least squares: the weighted mean of the two estimates."""
        return (w_pred * H_pred + H_prev + dH * dt) / (1.0 + w_pred)


def _cross(w: np.ndarray, r: np.ndarray) -> np.ndarray:
    """w x r_i for one vector w (3,) and points r (n,3), as r @ [w]x^T (one small product)."""
    x, y, z = w.tolist()
    return r @ np.array([[0.0, z, -y], [-z, 0.0, x], [y, -x, 0.0]])


def rigid_fit(v: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares rigid motion (c, v_c, w) of points p (n,3) moving with v (n,3), such that
    v_i ~ v_c + w x (p_i - c); w = 0 for fewer than two points (a rotation is not observable)."""
    n = len(p)
    c, vc = p.sum(axis=0) / n, v.sum(axis=0) / n
    if n < 2:
        return c, vc, np.zeros(3)
    r = p - c
    # sum_i |w x r_i - (v_i - vc)|^2: normal matrix sum_i (|r_i|^2 I - r_i r_i^T), right side sum_i r_i x u_i
    S, C = r.T @ r, (r.T @ (v - vc)).tolist()
    b = (C[1][2] - C[2][1], C[2][0] - C[0][2], C[0][1] - C[1][0])
    return c, vc, _solve_sym3(S, b)


def _solve_sym3(S: np.ndarray, b: tuple[float, float, float]) -> np.ndarray:
    """w with (tr(S) I - S) w = b, S (3,3) symmetric, by the adjugate in plain floats (this runs
    every policy step; np.linalg.solve's call overhead is most of its cost at 3 x 3). A tiny
    ridge: points on a line leave the spin about it unobservable; it stays zero, as with lstsq."""
    (s00, s01, s02), (_, s11, s12), (_, _, s22) = S.tolist()
    k = (s00 + s11 + s22) * (1.0 + 2e-9) + 1e-12
    a, d, f, u, x, y = k - s00, k - s11, k - s22, -s01, -s02, -s12  # [[a,u,x],[u,d,y],[x,y,f]]
    A00, A01, A02 = d * f - y * y, x * y - u * f, u * y - x * d
    A11, A12, A22 = a * f - x * x, u * x - a * y, a * d - u * u
    det = a * A00 + u * A01 + x * A02
    bx, by, bz = b
    return np.array([A00 * bx + A01 * by + A02 * bz, A01 * bx + A11 * by + A12 * bz,
                     A02 * bx + A12 * by + A22 * bz]) / det


def follow_bodies(v: np.ndarray, p: np.ndarray, trusted: np.ndarray, bodies: np.ndarray) -> np.ndarray:
    """Velocities of points the network was not trained for at this step (unobserved now or next,
    7.2.5: their losses are masked) replaced by the rigid motion of their body fitted to its
    trusted points; bodies without a trusted point keep the network's velocities. Returns ``v``
    itself when every point is trusted.
    v, p (P,3), trusted (P,) bool, bodies (P,) int (each hand and object one body)."""
    if trusted.all():
        return v
    out = v.copy()
    for b in set(bodies[~trusted].tolist()):
        idx = np.flatnonzero(bodies == b)
        seen, hidden = idx[trusted[idx]], idx[~trusted[idx]]
        if len(seen):
            c, vc, w = rigid_fit(v[seen], p[seen])
            out[hidden] = vc + _cross(w, p[hidden] - c)
    return out


def rigid_velocities(v: np.ndarray, p: np.ndarray, groups: np.ndarray) -> np.ndarray:
    """Point velocities (K,3) projected onto rigid-body motions, one per group: the least-squares
    (v_c, w) with v_i = v_c + w x (p_i - c); keypoints of one object cannot move apart."""
    out = np.empty_like(v)
    for g in np.unique(groups):
        idx = np.flatnonzero(groups == g)
        c, vc, w = rigid_fit(v[idx], p[idx])
        out[idx] = vc + _cross(w, p[idx] - c)
    return out
