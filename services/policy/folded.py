"""The trained network folded for the compiled rollout (compiled.py): the same function, fewer weights.

Every geometric input of ``PolicyNet`` (hand points relative to the wrist, anchor pair
translations, anchor heights) is a difference of two coordinates times a scale, so the
standardization and the first dense layer fold into one matrix acting on the raw positions:

    W1 ((x - mean) / std) = (W1 / std) T pos - (W1 / std) mean        (every feature observed)

which shrinks the first layer from n_in (~1000) to 3P (~150) columns. Features masked this step
(7.2.5: their normalized value is zero) are taken back out exactly: the loop subtracts the rows of
the features a hidden point takes part in (``lin_rows``) and its own mask input's row
(``mask_rows``). Output rows the control loop does not read (the pair translations) are dropped
from the head. Weights stay float32: at batch size one the folded net (about 9 MB) is read from
the L3 cache instead of memory.
"""

from __future__ import annotations

import numpy as np
import torch

from services.policy.network import PolicyNet


class FoldedNet:
    """The arrays of a ``PolicyNet`` in eval mode that the compiled loop runs: the folded first layer,
    the hidden layers and the head rows of ``keys`` (laid out as ``slices``). Built once per set of
    weights."""

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
            geo, _ = net.geometry(eye, torch.zeros_like(eye), ones)
            n_lin = net.n_geo - 3 * P - P  # local, pairs, heights
            T = geo[:, :n_lin].double().T  # (n_lin, 3P)
            mask0 = n_lin + 3 * P  # after the velocity slots (masked off) the masks; then tactile, glove mask,
            # memory and the time window's offsets: used as they are (compiled.py computes the window's)
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
        n_in = net.n_in
        # the mask inputs (1 = observed) as if every point were observed; a masked point's own 1 -> 0
        # is taken out with its features below
        small0 = mask0 + P
        c = c + G[:, mask0:small0] @ (1.0 - mean[mask0:small0])
        cols.append(G[:, small0:n_in])
        self.mean_small = mean[small0:n_in].numpy()
        self.W1 = torch.cat(cols, dim=1).float().numpy()
        self.b1 = c.float().numpy()
        # per-feature masks from per-point masks, as PolicyNet.geometry builds them
        self.m_a = np.concatenate([net.m_local.numpy(), net.m_pi.numpy(), net.anchors.numpy()])
        self.m_b = np.concatenate([net.m_wrist.numpy(), net.m_pj.numpy(), net.anchors.numpy()])
        # the first-layer rows of each linear feature and of each point's mask input: what a hidden
        # point's features take out again
        self.G_lin_rows = G[:, :n_lin].T.float().contiguous().numpy()
        self.mask_rows = G[:, mask0:small0].T.float().contiguous().numpy()
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
