"""The trained network folded for batch-one inference (P4): the same function, fewer weights.
A batch of position sets sharing everything else (turned copies of one scene) also goes through.

Every geometric input of ``PolicyNet`` (hand points relative to the wrist, anchor pair
translations, anchor heights, velocities) is a difference of two coordinates times a scale, so
the standardization and the first dense layer fold into one matrix acting on the raw positions:

    W1 ((x - mean) / std) = (W1 / std) T pos - (W1 / std) mean        (every feature observed)

which shrinks the first layer from n_in (~1000) to 3P (~150) columns. Features masked this step
(7.2.5: their normalized value is zero) are taken back out exactly: each point keeps the rows of
the features it takes part in, contiguous, so a masked point costs one read of its own rows. Output
rows the control loop does not read (the pair translations when their constraint weight is zero)
are dropped from the head. Weights stay float32: at batch size one the folded net (about 9 MB) is
read from the L3 cache instead of memory. The products run on numpy's BLAS, which took about half
the time of torch's for these shapes on the hosts measured (docs/policy.md, Inference speed).

Configurations whose inputs are not linear in the positions (side models, 7.8-normalized input
pairs, the recurrent branch reading the whole input) are not folded (``foldable`` is False) and
keep the plain forward pass.
"""

from __future__ import annotations

import numpy as np
import torch

from services.policy.network import TACTILE_SCALE, VEL_SCALE, PolicyNet


def foldable(net: PolicyNet) -> bool:
    c = net.cfg
    return not (c.tactile_model or c.object_model or c.recurrent or c.pair_input_eps > 0)


class FoldedNet:
    """Forward pass of a ``PolicyNet`` in eval mode for one state; outputs as ``PolicyNet.forward``
    (only the keys in ``keys``). Built once per set of weights; one input buffer, so one caller
    (thread) at a time."""

    def __init__(self, net: PolicyNet, keys: tuple[str, ...]) -> None:
        cfg, P = net.cfg, net.layout.P
        self.cfg, self.P = cfg, P
        with torch.no_grad():
            W1 = net.trunk[0].weight.double()
            b1 = net.trunk[0].bias.double()
            mean, std = net.mean.double(), net.std.double()
            G = W1 / std  # (hidden, n_in): the standardization folded into the first layer
            # the geometric features as a linear map of the flat positions, read off the net itself
            eye = torch.eye(3 * P, dtype=torch.float32).reshape(3 * P, P, 3)
            ones = torch.ones(3 * P, P)
            geo, _ = net.geometry(eye, torch.zeros_like(eye), ones, ones)
            n_lin = net.n_geo - 3 * P - P  # local, pairs, heights
            T = geo[:, :n_lin].double().T  # (n_lin, 3P)
            vel0 = n_lin
            mask0 = vel0 + 3 * P  # then the masks; then tactile, glove mask, memory, phase: used as they are
        # each linear feature is s * (pos[plus] - pos[minus]) (minus = 3P: a zero)
        Tn = T.numpy()
        plus = np.argmax(Tn > 0, axis=1)
        minus = np.where((Tn < 0).any(axis=1), np.argmax(Tn < 0, axis=1), 3 * P)
        scale = Tn[np.arange(n_lin), plus]
        rebuilt = np.zeros_like(Tn)
        rebuilt[np.arange(n_lin), plus] += scale
        ok = minus < 3 * P
        rebuilt[np.arange(n_lin)[ok], minus[ok]] -= scale[ok]
        if not np.allclose(rebuilt, Tn):
            raise ValueError("geometric inputs are not coordinate differences; cannot fold")
        self.plus, self.minus, self.scale = plus, minus, scale
        self.mean_lin = mean[:n_lin].numpy()
        A = G[:, :n_lin] @ T
        c = b1 - G[:, :n_lin] @ mean[:n_lin]
        cols = [A]
        self.vel_input = cfg.velocity_input
        if self.vel_input:  # masked by the velocity mask, as the geometry by the point mask
            cols.append(G[:, vel0:mask0] * VEL_SCALE)
            c = c - G[:, vel0:mask0] @ mean[vel0:mask0]
            self.mean_vel = mean[vel0:mask0].numpy()
        n_in = net.n_in
        # the mask inputs (1 = observed) as if every point were observed; a masked point's own 1 -> 0
        # is taken out with its features below
        small0 = mask0 + P
        c = c + G[:, mask0:small0] @ (1.0 - mean[mask0:small0])
        cols.append(G[:, small0:n_in])
        self.mean_small = mean[small0:n_in].numpy()
        self.W1 = torch.cat(cols, dim=1).float().numpy()
        self.b1 = c.float().numpy()
        self.G_vel_rows = G[:, vel0:mask0].T.float().contiguous().numpy() if self.vel_input else None
        # per-feature masks from per-point masks, as PolicyNet.geometry builds them
        self.m_a = np.concatenate([net.m_local.numpy(), net.m_pi.numpy(), net.anchors.numpy()])
        self.m_b = np.concatenate([net.m_wrist.numpy(), net.m_pj.numpy(), net.anchors.numpy()])
        # the first-layer rows of every feature a point takes part in, contiguous per point, so a
        # masked point costs one read of its own rows (a gather of scattered rows costs a copy)
        rows = G[:, :n_lin].T.float()
        self.point_features = [np.flatnonzero((self.m_a == p) | (self.m_b == p)) for p in range(P)]
        mask_rows = G[:, mask0:small0].T.float()
        self.point_rows = [torch.cat([rows[torch.from_numpy(f)], mask_rows[p:p + 1]]).contiguous().numpy()
                           for p, f in enumerate(self.point_features)]
        self.point_terms = [(plus[f], minus[f], scale[f], mean[:n_lin].numpy()[f]) for f in self.point_features]
        self._d = [np.ones((1, len(f) + 1), np.float32) for f in self.point_features]  # the last 1: the mask input
        self.G_lin_rows = rows.contiguous().numpy()
        self.m_vel = net.m_vel.numpy()
        linears = [m for m in net.trunk if isinstance(m, torch.nn.Linear)]
        self.layers = [(m.weight.detach().numpy().copy(), m.bias.detach().numpy().copy()) for m in linears[1:]]
        head_rows, self.slices, width = [], {}, 0
        for key in keys:
            s = net.slices[key]
            head_rows.append(torch.arange(s.start, s.stop))
            self.slices[key] = slice(width, width + s.stop - s.start)
            width += s.stop - s.start
        idx = torch.cat(head_rows)
        self.head_w = net.head.weight.detach()[idx].numpy().copy()
        self.head_b = net.head.bias.detach()[idx].numpy().copy()
        self.tactile, self.memory, self.phase = cfg.tactile, cfg.memory, cfg.phase_input
        self._rows(1)

    def _rows(self, B: int) -> None:
        """Input buffers for B rows: float32 inputs (no allocation per call), and the
        positions with a zero appended (the "minus" of a height feature)."""
        self._x = np.zeros((B, self.W1.shape[1]), np.float32)
        self._z = np.zeros((B, 3 * self.P + 1))

    def __call__(self, pos: np.ndarray, vel: np.ndarray, mask: np.ndarray, vmask: np.ndarray,
                 tactile: np.ndarray | None = None, tmask: np.ndarray | None = None,
                 H: np.ndarray | None = None, t: float = 0.0) -> dict[str, np.ndarray]:
        """pos, vel (P,3) metres and m/s, or (B,P,3): B position sets (turned copies of one scene)
        sharing the masks, touch, memory and time; mask, vmask (P,) bool. Returns float64 outputs,
        (B, n) where a batch was given."""
        batched = pos.ndim == 3
        flat = pos.reshape(len(pos) if batched else 1, -1)
        B, n = flat.shape
        if len(self._x) != B:
            self._rows(B)
        x = self._x
        x[:, :n] = flat
        i = n
        if self.vel_input:  # VEL_SCALE is folded into its columns
            x[:, i:i + n] = vel.reshape(B, -1)
            i += n
        # the inputs used as they are, minus their mean (their std is folded into W1)
        start = i
        if self.tactile:
            tm = tmask.reshape(-1)
            tactile_at = i
            x[:, i:i + tm.size] = tactile.reshape(-1) * TACTILE_SCALE
            x[:, i + tm.size:i + 2 * tm.size] = tm
            i += 2 * tm.size
        if self.memory:
            x[:, i:i + len(H)] = H
            i += len(H)
        if self.phase:
            x[:, i] = t
        x[:, start:] -= self.mean_small
        if self.tactile:  # a masked tactile reading is zero after normalization
            x[:, tactile_at:tactile_at + tm.size] *= tm
        h = x @ self.W1.T
        h += self.b1
        hidden = np.flatnonzero(~mask)
        if len(hidden):  # masked features: their normalized value is zero, not (x - mean) / std
            z = self._z
            z[:, :-1] = flat
            for p in hidden:
                plus, minus, scale, mean = self.point_terms[p]
                d = self._d[p] if B == 1 else np.ones((B, len(plus) + 1), np.float32)  # last 1: mask input
                d[:, :-1] = scale * (z[:, plus] - z[:, minus]) - mean
                h -= d @ self.point_rows[p]
            if len(hidden) > 1:  # a feature of two masked points was taken out twice
                twice = np.flatnonzero(~mask[self.m_a] & ~mask[self.m_b] & (self.m_a != self.m_b))
                if len(twice):
                    d = self.scale[twice] * (z[:, self.plus[twice]] - z[:, self.minus[twice]]) - self.mean_lin[twice]
                    h += d.astype(np.float32) @ self.G_lin_rows[twice]
        if self.vel_input:
            voff = np.flatnonzero(~vmask[self.m_vel])
            if len(voff):
                d = vel.reshape(B, -1)[:, voff] * VEL_SCALE - self.mean_vel[voff]
                h -= d.astype(np.float32) @ self.G_vel_rows[voff]
        np.maximum(h, 0.0, out=h)
        for W, b in self.layers:
            h = h @ W.T
            h += b
            np.maximum(h, 0.0, out=h)
        out = (h @ self.head_w.T + self.head_b).astype(np.float64)
        return {k: out[:, s] if batched else out[0, s] for k, s in self.slices.items()}
