"""The network of thesis 7.2; its variants are the switches of ``ModelConfig`` (config.py).

Inputs (7.2.1, 7.2.3, 7.2.5): each hand's points relative to its wrist, pairwise translations
between anchors (wrists, fingertips, object points), anchor heights (gravity matters, 7.2.4),
observed masks, tactile with its glove mask (7.2.10), reservoir activations (7.2.8) and, with a time
window (row 4 of Table 7.1, window.py), each older block's mean position relative to the current
position (masked where the point is unobserved now or anywhere in the block). Inputs are
standardized with training statistics and multiplied by their masks after normalization (7.2.5).
The input vector keeps a block of 3P keypoint-velocity slots whose mask is always zero: the
trained presets' first layer has those columns, and the statistics and initial weights are drawn
for that width.

Trunk: dense 2048-512-512-512 ReLU; one linear output layer holding every output: keypoint
velocities, mask logits, next tactile, denoised reservoir value and rate (7.9-7.10), next pairwise
translations (7.8, an auxiliary training target) and the object dynamics matrix J_D (7.13).

J_D here maps each hand's pinch-point velocity (thumb and index tips) to every object point
velocity with one scalar per (object point, hand), i.e. J_D = j (x) I_3: rotation about gravity
leaves it unchanged, and a 16-number output replaces a 24x126 matrix.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
from torch import nn

from services.policy.config import ModelConfig
from services.policy.window import check_blocks
from shared.demo import KEYPOINTS_PER_HAND, TACTILE_REGIONS

POS_SCALE = 10.0  # 10 cm -> 1
VEL_SCALE = 5.0  # 0.2 m/s -> 1
TACTILE_SCALE = 0.05  # 20 kPa -> 1
PAIR_SCALE = 50.0  # next-step pair translation change: 2 cm -> 1
HAND_ANCHORS = (0, 4, 8, 12, 16, 20)  # wrist and fingertips
PINCH = (4, 8)  # thumb and index tips
REGIONS = len(TACTILE_REGIONS)
HAND_POINTS = 2 * KEYPOINTS_PER_HAND


def _mlp(sizes: list[int], act: type[nn.Module], dropout: float = 0.0, last_act: bool = False) -> nn.Sequential:
    layers: list[nn.Module] = []
    for i in range(len(sizes) - 1):
        layers.append(nn.Linear(sizes[i], sizes[i + 1]))
        if i < len(sizes) - 2 or last_act:
            layers.append(act())
            if dropout:
                layers.append(nn.Dropout(dropout))
    return nn.Sequential(*layers)


@dataclass
class Layout:
    """Index bookkeeping for P = 42 + K points; shared by the network and the consistency solve."""

    K: int
    anchors: np.ndarray = field(init=False)
    pair_i: np.ndarray = field(init=False)
    pair_j: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        hand = [h * KEYPOINTS_PER_HAND + k for h in range(2) for k in HAND_ANCHORS]
        self.anchors = np.array(hand + list(range(HAND_POINTS, HAND_POINTS + self.K)))
        self.pair_i, self.pair_j = np.triu_indices(len(self.anchors), 1)

    @property
    def P(self) -> int:
        return HAND_POINTS + self.K

    @property
    def pairs(self) -> int:
        return len(self.pair_i)

    @property
    def pinch(self) -> np.ndarray:
        return np.array([[h * KEYPOINTS_PER_HAND + k for k in PINCH] for h in range(2)])


class PolicyNet(nn.Module):
    """Features -> trunk -> all outputs."""

    def __init__(self, cfg: ModelConfig, K: int) -> None:
        super().__init__()
        check_blocks(cfg.window)
        self.cfg, self.layout = cfg, Layout(K)
        lay = self.layout
        self.register_buffer("anchors", torch.as_tensor(lay.anchors))
        self.register_buffer("pi", torch.as_tensor(lay.pair_i))
        self.register_buffer("pj", torch.as_tensor(lay.pair_j))
        self.register_buffer("pinch", torch.as_tensor(lay.pinch))
        # gathers that expand per-point masks to per-feature masks (one indexing op each at inference)
        wrist = (np.arange(HAND_POINTS) // KEYPOINTS_PER_HAND) * KEYPOINTS_PER_HAND
        self.register_buffer("m_local", torch.as_tensor(np.repeat(np.arange(HAND_POINTS), 3)))
        self.register_buffer("m_wrist", torch.as_tensor(np.repeat(wrist, 3)))
        self.register_buffer("m_pi", torch.as_tensor(np.repeat(lay.anchors[lay.pair_i], 3)))
        self.register_buffer("m_pj", torch.as_tensor(np.repeat(lay.anchors[lay.pair_j], 3)))
        self.register_buffer("m_vel", torch.as_tensor(np.repeat(np.arange(lay.P), 3)))
        n_geo = HAND_POINTS * 3 + lay.pairs * 3 + len(lay.anchors) + lay.P * 3 + lay.P
        self.n_window = max(len(cfg.window) - 1, 0) * lay.P * 3
        n_in = n_geo + (2 * 2 * REGIONS if cfg.tactile else 0) + (cfg.reservoir if cfg.memory else 0) + self.n_window
        self.n_geo, self.n_in = n_geo, n_in
        self.register_buffer("mean", torch.zeros(n_in))
        self.register_buffer("std", torch.ones(n_in))
        self.register_buffer("H_mean", torch.zeros(max(cfg.reservoir, 1)))
        self.register_buffer("H_std", torch.ones(max(cfg.reservoir, 1)))
        self.register_buffer("dH_std", torch.ones(max(cfg.reservoir, 1)))
        self.register_buffer("H0", torch.zeros(max(cfg.reservoir, 1)))
        self.trunk = _mlp([n_in, *cfg.hidden], nn.ReLU, last_act=True)
        self.slices: dict[str, slice] = {}
        width = 0
        for key, n, on in (("vel", lay.P * 3, True), ("mask", lay.P, cfg.masks), ("tactile", 2 * REGIONS, cfg.tactile),
                           ("H", cfg.reservoir, cfg.memory), ("dH", cfg.reservoir, cfg.memory),
                           ("pairs", lay.pairs * 3, cfg.pair_outputs), ("J", lay.K * 2, cfg.dynamics)):
            if on:
                self.slices[key] = slice(width, width + n)
                width += n
        self.head = nn.Linear(cfg.hidden[-1], width)

    # --- inputs ------------------------------------------------------------------------------
    def geometry(self, pos: torch.Tensor, vel: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Raw geometric features and their masks. pos, vel (B,P,3); mask (B,P) float."""
        B = pos.shape[0]
        hands = pos[:, :HAND_POINTS].reshape(B, 2, KEYPOINTS_PER_HAND, 3)
        local = (hands - hands[:, :, :1]).reshape(B, -1)
        a = pos[:, self.anchors]
        pairs = (a[:, self.pj] - a[:, self.pi]).reshape(B, -1)
        feats = torch.cat([torch.cat([local, pairs, a[:, :, 2]], dim=1) * POS_SCALE, vel.reshape(B, -1) * VEL_SCALE,
                           mask], dim=1)
        fmask = torch.cat([mask[:, self.m_local] * mask[:, self.m_wrist], mask[:, self.m_pi] * mask[:, self.m_pj],
                           mask[:, self.anchors], torch.zeros_like(mask[:, self.m_vel]),  # velocity slots: off
                           torch.ones_like(mask)], dim=1)
        return feats, fmask

    def inputs(self, pos: torch.Tensor, vel: torch.Tensor, mask: torch.Tensor, tactile: torch.Tensor | None = None,
               tmask: torch.Tensor | None = None, H: torch.Tensor | None = None,
               window: torch.Tensor | None = None, wmask: torch.Tensor | None = None) -> torch.Tensor:
        """Normalized, masked input vector (B, n_in). ``window`` (B, blocks-1, P, 3): the older blocks'
        mean positions, ``wmask`` (B, blocks-1, P) whether each observed its points throughout."""
        cfg = self.cfg
        geo, gmask = self.geometry(pos, vel, mask)
        parts, masks = [geo], [gmask]
        if cfg.tactile:
            t_in = tactile.reshape(len(geo), -1) * TACTILE_SCALE
            tm = tmask.reshape(len(geo), -1)
            parts += [t_in, tm]
            masks += [tm, torch.ones_like(tm)]
        if cfg.memory:
            parts.append(H)
            masks.append(torch.ones_like(H))
        if self.n_window:
            if window is None or wmask is None:
                raise ValueError(f"a time-window net ({cfg.window}) needs the window's block means and masks")
            B = len(geo)
            parts.append(((window - pos[:, None]) * POS_SCALE).reshape(B, -1))
            masks.append((wmask * mask[:, None]).repeat_interleave(3, dim=2).reshape(B, -1))
        x = torch.cat(parts, dim=1)
        return (x - self.mean) / self.std * torch.cat(masks, dim=1)

    def forward(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        out = self.head(self.trunk(x))
        return {k: out[:, s] for k, s in self.slices.items()}

    def set_statistics(self, x: torch.Tensor) -> None:
        self.mean.copy_(x.mean(0))
        self.std.copy_(x.std(0).clamp_min(1e-2))
