"""The policy's recursive rollout compiled with numba (P4): a whole horizon, or one step, in one call.

This is the one inference path of the served policy: each step runs the folded forward pass
(folded.py), the 7.2.5 mask handling, the 7.15 dynamics reconciliation, the integral of 7.5, the
7.9-7.10 memory solve and the tactile feedback in one compiled loop. A step of the same in Python
and numpy spent about half of its time in call overhead around the folded network's products, so
a 1 s horizon of 50 sequential steps could not get near 10 ms that way. Dense layers are written
as sums of weight rows over the nonzero inputs: after a ReLU most inputs are zero, so most rows
are never read, and each row read is a contiguous vectorized update.

``evaluation/reference.py`` is the same step on the torch network (the reference this loop is
tested against: tests/unit/test_policy_inference.py).
"""

from __future__ import annotations

import numba
import numpy as np

from services.policy.folded import FoldedNet
from services.policy.network import POS_SCALE, TACTILE_SCALE, VEL_SCALE
from services.policy.window import block_starts, history_length

OK, NET_NAN, POS_NAN = 0, 1, 2


class CompiledRollout:
    """Arrays of one folded network and config, laid out for ``_rollout``; rebuilt with the folded net."""

    def __init__(self, model, fold: FoldedNet, max_tactile: float) -> None:
        """``model``: the ``model.Policy`` whose network ``fold`` was folded from."""
        cfg, inf, P = model.cfg, model.inference, fold.P
        self.fold, self.P = fold, P
        self.w1t = np.ascontiguousarray(fold.W1.T)  # (inputs, hidden): one row per input
        self.b1 = fold.b1
        # the hidden layers after the first, transposed and packed flat: (inputs, outputs) per layer
        none = [np.zeros(0, np.float32)]  # a net with one hidden layer
        self.hidden_w = np.concatenate([W.T.ravel() for W, _ in fold.layers] or none).astype(np.float32)
        self.hidden_b = np.concatenate([b for _, b in fold.layers] or none).astype(np.float32)
        self.hidden_shape = np.array([W.T.shape for W, _ in fold.layers], np.int64).reshape(-1, 2)
        self.head_t, self.head_b = np.ascontiguousarray(fold.head_w.T), fold.head_b
        n_lin = len(fold.plus)
        self.lin = (fold.plus.astype(np.int64), fold.minus.astype(np.int64), fold.scale.astype(np.float64),
                    fold.mean_lin.astype(np.float64), fold.m_a.astype(np.int64)[:n_lin],
                    fold.m_b.astype(np.int64)[:n_lin], fold.G_lin_rows)
        self.mask_rows = fold.mask_rows
        self.mean_small = fold.mean_small.astype(np.float32)

        def part(key: str) -> tuple[int, int]:
            s = fold.slices.get(key)
            return (s.start, s.stop) if s is not None else (0, 0)

        self.parts = np.array([part(k) for k in ("vel", "J", "mask", "tactile", "H", "dH")], np.int64)
        if cfg.dynamics:
            pool = model.pool_matrix() if cfg.body_dynamics else np.eye(model.K)
        else:
            pool = np.zeros((model.K, model.K))
        self.pool = np.ascontiguousarray(pool, dtype=np.float64)
        self.pinch = np.asarray(model.net.layout.pinch, np.int64)
        self.body = np.asarray(model.body, np.int64)
        self.flags = np.array([cfg.masks, cfg.masks and inf.follow_unobserved, cfg.dynamics, cfg.tactile,
                               cfg.memory], np.bool_)
        if cfg.memory:
            self.dH_gain = (model.net.dH_std / model.net.H_std).numpy().astype(np.float64)
        else:
            self.dH_gain = np.zeros(0)
        self.w_prior, self.vmax, self.max_tactile = float(inf.w_memory_prior), float(inf.max_speed), max_tactile
        self.window = tuple(cfg.window)  # the time window's older blocks: first history index and length of each
        self.w_start = block_starts(self.window)
        self.w_len = np.array(self.window[:-1], np.int64)

    def __call__(self, state: dict, steps: int, dt: float, w_dyn: float
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
        """Rolls ``steps`` steps of ``dt`` from ``state``. Returns positions (S,P,3), tactile
        (S,2,R), memory (S,size), the observed-point mask after the last step (P,) and a status
        (OK, NET_NAN, POS_NAN). A time-window net reads ``state``'s history (window_pos, window_mask:
        model.Policy.start_window) and carries it along the steps."""
        tact0 = np.ascontiguousarray(state["tactile"], dtype=np.float64).reshape(-1)
        H0 = np.ascontiguousarray(state["H"], dtype=np.float64) if "H" in state else np.zeros(0)
        pos = np.empty((steps, self.P, 3))
        tact = np.empty((steps, tact0.size))
        mem = np.empty((steps, H0.size))
        mask = np.array(state["mask"], np.bool_)  # a copy: the loop updates it in place
        if self.window:
            if "window_pos" not in state or "window_mask" not in state:
                raise ValueError(f"a time-window net ({self.window}) needs the state's window history "
                                 f"(Policy.start_window)")
            hist = np.ascontiguousarray(state["window_pos"], dtype=np.float64)
            hist_mask = np.ascontiguousarray(state["window_mask"], dtype=np.bool_)
            if hist.shape != (history_length(self.window), self.P, 3) or hist_mask.shape != hist.shape[:2]:
                raise ValueError(f"window history {hist.shape} / {hist_mask.shape}; the window {self.window} "
                                 f"needs ({history_length(self.window)}, {self.P}, 3)")
        else:
            hist, hist_mask = np.zeros((0, self.P, 3)), np.zeros((0, self.P), np.bool_)
        status = _rollout(np.ascontiguousarray(state["pos"], dtype=np.float64), tact0,
                          np.ascontiguousarray(state["tmask"], dtype=np.float64).reshape(-1), H0,
                          mask, steps, float(dt), float(w_dyn), self.w1t,
                          self.b1, self.hidden_w, self.hidden_b, self.hidden_shape, self.head_t, self.head_b,
                          *self.lin, self.mask_rows, self.mean_small, self.parts, self.pool, self.pinch, self.body,
                          self.flags, self.dH_gain, self.w_prior, self.vmax, self.max_tactile, TACTILE_SCALE,
                          VEL_SCALE, self.w_start, self.w_len, hist, hist_mask, POS_SCALE, pos, tact, mem)
        return pos, tact.reshape(steps, 2, -1), mem, mask, int(status)


def warm() -> None:
    """Compiles ``_rollout`` (about 20 s on first use; numba caches the machine code next to this
    file) by running it on a two-point dummy with the argument types ``CompiledRollout`` passes,
    so a service does not stall on its first horizon. Run by the install step and at service start."""
    f32, i64 = np.float32, np.int64
    P, K, H = 2, 1, 1
    _rollout(np.zeros((P, 3)), np.zeros(2), np.zeros(2), np.zeros(H), np.ones(P, np.bool_), 1, 0.02, 1.0,
             np.zeros((3 * P + 2 + H, 4), f32), np.zeros(4, f32), np.zeros(16, f32), np.zeros(4, f32),
             np.array([[4, 4]], i64), np.zeros((4, 3 * P + K * 2 + P + 2 + 2 * H), f32),
             np.zeros(3 * P + K * 2 + P + 2 + 2 * H, f32), np.zeros(1, i64), np.full(1, 3 * P, i64),
             np.ones(1), np.zeros(1), np.zeros(1, i64), np.zeros(1, i64), np.zeros((1, 4), f32),
             np.zeros((P, 4), f32), np.zeros(2 + H, f32),
             np.array([[0, 6], [6, 8], [8, 10], [10, 12], [12, 13], [13, 14]], i64), np.eye(K), np.zeros((2, 2), i64),
             np.array([0, 1], i64), np.ones(5, np.bool_), np.ones(H), 0.01, 1.5, 500.0, TACTILE_SCALE, VEL_SCALE,
             np.zeros(0, i64), np.zeros(0, i64), np.zeros((0, P, 3)), np.zeros((0, P), np.bool_), POS_SCALE,
             np.zeros((1, P, 3)), np.zeros((1, 2)), np.zeros((1, H)))


@numba.njit(cache=True)
def _dense_relu(x: np.ndarray, wt: np.ndarray, b: np.ndarray, relu: bool) -> np.ndarray:
    """b + x @ wt over the nonzero entries of x (rows of wt are contiguous), then a ReLU."""
    h = b.copy()
    n = h.size
    for j in range(x.size):
        xj = x[j]
        if xj != 0.0:
            for i in range(n):
                h[i] += xj * wt[j, i]
    if relu:
        for i in range(n):
            if h[i] < 0.0:
                h[i] = 0.0
    return h


@numba.njit(cache=True)
def _solve_sym3(S: np.ndarray, b0: float, b1: float, b2: float) -> np.ndarray:
    """evaluation.reference._solve_sym3, the same arithmetic."""
    s00, s01, s02, s11, s12, s22 = S[0, 0], S[0, 1], S[0, 2], S[1, 1], S[1, 2], S[2, 2]
    k = (s00 + s11 + s22) * (1.0 + 2e-9) + 1e-12
    a, d, f, u, x, y = k - s00, k - s11, k - s22, -s01, -s02, -s12
    A00, A01, A02 = d * f - y * y, x * y - u * f, u * y - x * d
    A11, A12, A22 = a * f - x * x, u * x - a * y, a * d - u * u
    det = a * A00 + u * A01 + x * A02
    w = np.empty(3)
    w[0] = (A00 * b0 + A01 * b1 + A02 * b2) / det
    w[1] = (A01 * b0 + A11 * b1 + A12 * b2) / det
    w[2] = (A02 * b0 + A12 * b1 + A22 * b2) / det
    return w


@numba.njit(cache=True)
def _follow_bodies(v: np.ndarray, p: np.ndarray, trusted: np.ndarray, body: np.ndarray) -> np.ndarray:
    """evaluation.reference.follow_bodies: untrusted points move rigidly with their body's trusted ones."""
    out = v.copy()
    for b in range(body.max() + 1):
        idx = np.flatnonzero(body == b)
        seen = idx[trusted[idx]]
        hidden = idx[~trusted[idx]]
        if hidden.size == 0 or seen.size == 0:
            continue
        n = seen.size
        c = np.zeros(3)
        vc = np.zeros(3)
        for i in seen:
            c += p[i]
            vc += v[i]
        c /= n
        vc /= n
        w = np.zeros(3)
        if n >= 2:  # evaluation.reference.rigid_fit: S = r^T r, C = r^T (v - vc)
            S = np.zeros((3, 3))
            C = np.zeros((3, 3))
            for i in seen:
                for a in range(3):
                    ra = p[i, a] - c[a]
                    for b in range(3):
                        S[a, b] += ra * (p[i, b] - c[b])
                        C[a, b] += ra * (v[i, b] - vc[b])
            w = _solve_sym3(S, C[1, 2] - C[2, 1], C[2, 0] - C[0, 2], C[0, 1] - C[1, 0])
        for i in hidden:
            q = p[i] - c
            out[i, 0] = vc[0] + w[1] * q[2] - w[2] * q[1]
            out[i, 1] = vc[1] + w[2] * q[0] - w[0] * q[2]
            out[i, 2] = vc[2] + w[0] * q[1] - w[1] * q[0]
    return out


@numba.njit(cache=True)
def _rollout(pos0, tact0, tmask, H0, mask, steps, dt, w_dyn, w1t, b1, hidden_w, hidden_b, hidden_shape, head_t, head_b,
             plus, minus, scale, mean_lin, m_a, m_b, lin_rows, mask_rows, mean_small, parts, pool, pinch, body,
             flags, dH_gain, w_prior, vmax, max_tactile, tactile_scale, vel_scale, w_start, w_len, hist_pos0,
             hist_mask0, pos_scale, pos_out, tact_out, mem_out):
    """The policy step ``steps`` times (folded forward pass + consistency solve), writing each step's
    positions, tactile and memory; ``mask`` is updated in place. ``w_start``/``w_len``: the time
    window's older blocks in the history ``hist_pos0`` (W-1,P,3) / ``hist_mask0`` (W-1,P), which the
    loop carries on (window.py). Returns the status."""
    masks, follow, dynamics, tactile, memory = flags[0], flags[1], flags[2], flags[3], flags[4]
    P = pos0.shape[0]
    K = pool.shape[0]
    n_hand = P - K
    pos = pos0.copy()
    tac = tact0.copy()
    H = H0.copy()
    hist = hist_pos0.copy()
    hist_mask = hist_mask0.copy()
    n_hist = hist.shape[0]
    n_pos, n_t = 3 * P, tac.size
    x = np.zeros(w1t.shape[0], np.float32)
    z = np.zeros(n_pos + 1)
    for s in range(steps):
        # --- the folded forward pass (the first layer folded by folded.FoldedNet) ---
        flat = pos.reshape(-1)
        for i in range(n_pos):
            x[i] = flat[i]
            z[i] = flat[i]
        i = n_pos
        if tactile:
            for j in range(n_t):
                x[i + j] = (np.float32(tac[j] * tactile_scale) - mean_small[j]) * np.float32(tmask[j])
                x[i + n_t + j] = np.float32(tmask[j]) - mean_small[n_t + j]
            i += 2 * n_t
        if memory:
            off = i - n_pos
            for j in range(H.size):
                x[i + j] = np.float32(H[j]) - mean_small[off + j]
            i += H.size
        if w_len.size > 0:  # window.block_means relative to the current positions, as PolicyNet.inputs
            off = i - n_pos
            for b in range(w_len.size):
                lo, hi = w_start[b], w_start[b] + w_len[b]
                for p in range(P):
                    seen = mask[p]
                    for q in range(lo, hi):
                        seen = seen and hist_mask[q, p]
                    for a in range(3):
                        m = 0.0
                        for q in range(lo, hi):
                            m += hist[q, p, a]
                        k = (b * P + p) * 3 + a
                        f = np.float32(np.float32(m / w_len[b] - pos[p, a]) * np.float32(pos_scale))
                        x[i + k] = (f - mean_small[off + k]) * np.float32(1.0 if seen else 0.0)
        h = _dense_relu(x, w1t, b1, False)
        if masks:  # masked features back to zero: each feature touching a hidden point, once
            for f in range(plus.size):
                if not (mask[m_a[f]] and mask[m_b[f]]):
                    d = np.float32(scale[f] * (z[plus[f]] - z[minus[f]]) - mean_lin[f])
                    h -= d * lin_rows[f]
            for p in range(P):
                if not mask[p]:
                    h -= mask_rows[p]
        for i in range(h.size):
            if h[i] < 0.0:
                h[i] = 0.0
        ow, ob = 0, 0
        for n_in, n_out in hidden_shape:
            h = _dense_relu(h, hidden_w[ow:ow + n_in * n_out].reshape(n_in, n_out), hidden_b[ob:ob + n_out], True)
            ow += n_in * n_out
            ob += n_out
        out = _dense_relu(h, head_t, head_b, False).astype(np.float64)
        for i in range(out.size):
            if not np.isfinite(out[i]):
                return NET_NAN
        # --- the consistency solve (evaluation.reference.reference_step) ---
        v = out[parts[0, 0]:parts[0, 1]].reshape(P, 3) / vel_scale
        v = np.minimum(np.maximum(v, -vmax), vmax)
        trusted = np.ones(P, np.bool_)
        if follow:
            for p in range(P):
                trusted[p] = mask[p] and out[parts[2, 0] + p] > 0.0
            keep = trusted.copy()
            if dynamics:
                keep[n_hand:] = True
            v = _follow_bodies(v, pos, keep, body)
        if dynamics and w_dyn > 0.0:
            Jnet = out[parts[1, 0]:parts[1, 1]].reshape(K, 2)
            vp = np.empty((2, 3))
            for k in range(2):
                vp[k] = 0.5 * (v[pinch[k, 0]] + v[pinch[k, 1]])
            for k in range(K):  # (pool @ J_net) @ v_pinch, 7.15
                for a in range(3):
                    jv = 0.0
                    for q in range(K):
                        jv += pool[k, q] * (Jnet[q, 0] * vp[0, a] + Jnet[q, 1] * vp[1, a])
                    v[n_hand + k, a] = (v[n_hand + k, a] + w_dyn * jv) / (1.0 + w_dyn)
            v = np.minimum(np.maximum(v, -vmax), vmax)
        else:
            v = np.minimum(np.maximum(v, -vmax), vmax)
        if follow and dynamics:
            keep = trusted.copy()
            keep[:n_hand] = True
            v = _follow_bodies(v, pos, keep, body)
        nxt = pos + v * dt
        if n_hist > 0:  # this step's sample joins the window's history (window.push_history)
            for q in range(n_hist - 1):
                hist[q] = hist[q + 1]
                hist_mask[q] = hist_mask[q + 1]
            hist[n_hist - 1] = pos
            hist_mask[n_hist - 1] = mask
        if masks:
            for p in range(P):
                mask[p] = out[parts[2, 0] + p] > 0.0
        if tactile:
            for j in range(n_t):
                tac[j] = min(max(out[parts[3, 0] + j] / tactile_scale, 0.0), max_tactile)
        if memory:
            for j in range(H.size):
                hp = out[parts[4, 0] + j]
                dh = out[parts[5, 0] + j] * dH_gain[j]
                H[j] = min(max((w_prior * hp + H[j] + dh * dt) / (1.0 + w_prior), -5.0), 5.0)
        for i in range(P):
            for k in range(3):
                if not np.isfinite(nxt[i, k]):
                    return POS_NAN
        pos = nxt
        pos_out[s] = pos
        tact_out[s] = tac
        mem_out[s] = H
    return OK
