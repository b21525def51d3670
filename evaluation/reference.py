"""The policy step on the torch network, in numpy and torch: the reference the served compiled loop
(services/policy/compiled.py) is tested and benchmarked against (thesis 7.3-7.5, 7.9-7.10, 7.15).

Each step: the network's velocities bounded to max_speed; points not trusted (unobserved now, or
predicted unobserved next) follow the rigid motion of their body's trusted points; object velocities
reconciled with the dynamics constraint (7.15)

    V_o = argmin |V_o - V_o,net|^2 + w_dyn |V_o - J_D V_pinch|^2

and bounded again; then the integral of 7.5 (P = P_prev + V dt); the memory by 7.9-7.10,
H = argmin w_H |H - H_P|^2 + |H - H_prev - dH_P dt|^2, bounded to +-5; tactile bounded to
[0, MAX_TACTILE_KPA].
"""

from __future__ import annotations

import numpy as np
import torch

from services.policy.model import MAX_TACTILE_KPA, Policy
from services.policy.network import TACTILE_SCALE, VEL_SCALE
from services.policy.window import block_means, push_history
from shared.demo import KEYPOINTS_PER_HAND


def network_outputs(policy: Policy, state: dict) -> dict[str, np.ndarray]:
    """The torch forward pass of one state (float64 outputs)."""
    net, s = policy.net, state
    vm = (s["mask"] if policy.cfg.masks else np.ones(len(s["mask"]), bool)).astype(np.float32)

    def t(x: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(x, dtype=np.float32))

    window = wmask = None
    if policy.cfg.window:
        means, seen = block_means(s["window_pos"], s["window_mask"], policy.cfg.window)
        window, wmask = t(means[None]), t(seen[None])
    with torch.inference_mode():
        x = net.inputs(t(s["pos"][None]), t(s["vel"][None]), t(vm[None]), t(s["tactile"][None]),
                       t(s["tmask"][None].astype(np.float32)), t(s["H"][None]) if policy.cfg.memory else None,
                       window, wmask)
        out = net(x)
    return {k: v[0].numpy().astype(np.float64) for k, v in out.items()}


def reference_step(policy: Policy, state: dict, dt: float | None = None) -> dict:
    """``Policy.step`` on the torch network: the next state (positions, velocities, mask, tactile,
    memory, time)."""
    cfg, inf = policy.cfg, policy.inference
    dt = dt or policy.dt
    out = network_outputs(policy, state)
    P, n = len(state["pos"]), 2 * KEYPOINTS_PER_HAND
    vmax = inf.max_speed
    v = np.clip(out["vel"].reshape(P, 3) / VEL_SCALE, -vmax, vmax)
    J = None
    if cfg.dynamics:
        J = out["J"].reshape(policy.K, 2)
        if cfg.body_dynamics:
            J = policy.pool_matrix() @ J
    trusted = None
    if cfg.masks and inf.follow_unobserved:
        trusted = state["mask"] & (out["mask"] > 0.0)
        hand = policy.body < 2  # with J the objects follow after their velocities are reconciled (below)
        v = follow_bodies(v, state["pos"], trusted | ~hand if J is not None else trusted, policy.body)
    if J is not None and inf.w_dyn > 0:  # 7.15
        lay = policy.net.layout
        pinch = 0.5 * (v[lay.pinch[:, 0]] + v[lay.pinch[:, 1]])  # (2,3) pinch-point velocities
        v = np.concatenate([v[:n], (v[n:] + inf.w_dyn * (J @ pinch)) / (1.0 + inf.w_dyn)])
    v = np.clip(v, -vmax, vmax)
    if trusted is not None and J is not None:  # object points unseen follow their reconciled object
        v = follow_bodies(v, state["pos"], trusted | hand, policy.body)
    pos = state["pos"] + v * dt
    nxt = dict(state, t=state.get("t", 0.0) + dt, vel=(pos - state["pos"]) / dt, pos=pos)
    if cfg.masks:
        nxt["mask"] = out["mask"] > 0.0
    if cfg.tactile:
        nxt["tactile"] = np.clip(out["tactile"].reshape(2, -1) / TACTILE_SCALE, 0.0, MAX_TACTILE_KPA)
    if cfg.memory:
        dH = out["dH"] * (policy.net.dH_std / policy.net.H_std).numpy()
        w = inf.w_memory_prior
        nxt["H"] = np.clip((w * out["H"] + state["H"] + dH * dt) / (1.0 + w), -5.0, 5.0)
    if cfg.window:
        nxt["window_pos"] = push_history(state["window_pos"], state["pos"])
        nxt["window_mask"] = push_history(state["window_mask"], state["mask"])
    return nxt


def reference_roll(policy: Policy, state: dict, steps: int, dt: float | None = None
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``Policy.roll`` on the torch network: positions (S,P,3), tactile (S,2,R), memory (S,size)."""
    pos, tact, mem = [], [], []
    for _ in range(steps):
        state = reference_step(policy, state, dt)
        pos.append(state["pos"])
        tact.append(state["tactile"])
        mem.append(state.get("H", np.zeros(0)))
    return np.array(pos), np.array(tact), np.array(mem)


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
