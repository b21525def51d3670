"""The network of thesis 7.2 on one code path; every variant is a switch of ``PolicyConfig``.

Inputs (7.2.1, 7.2.3, 7.2.5): each hand's points relative to its wrist, pairwise translations
between anchors (wrists, fingertips, object points), anchor heights (gravity matters, 7.2.4),
keypoint velocities, observed masks, tactile with its glove mask (7.2.10), reservoir activations
(7.2.8) and, with ``recurrent``, the recurrent branch's feedback (7.2.6). Inputs are standardized
with training statistics and multiplied by their masks after normalization (7.2.5).

Trunk: dense 2048-512-512-512 ReLU; one linear output layer holding every output: keypoint
velocities, mask logits, next tactile, denoised reservoir value and rate (7.9-7.10), next pairwise
translations (7.8) and the object dynamics matrix J_D (7.13). Side models (7.2.9): a tactile model
(3 tanh layers of 64) and an object-state model (3 tanh layers of 32, predicting object keypoint
velocities), both fed the policy's non-tactile inputs.

J_D here maps each hand's pinch-point velocity (thumb and index tips) to every object point
velocity with one scalar per (object point, hand), i.e. J_D = j (x) I_3: rotation about gravity
leaves it unchanged, and a 16-number output replaces a 24x126 matrix.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, fields

import numpy as np
import torch
from torch import nn

from shared.demo import KEYPOINTS_PER_HAND, TACTILE_REGIONS

POS_SCALE = 10.0  # 10 cm -> 1
VEL_SCALE = 5.0  # 0.2 m/s -> 1
TACTILE_SCALE = 0.05  # 20 kPa -> 1
PAIR_SCALE = 50.0  # next-step pair translation change: 2 cm -> 1
HAND_ANCHORS = (0, 4, 8, 12, 16, 20)  # wrist and fingertips
PINCH = (4, 8)  # thumb and index tips
REGIONS = len(TACTILE_REGIONS)
HAND_POINTS = 2 * KEYPOINTS_PER_HAND


@dataclass
class PolicyConfig:
    name: str = "multimodal"
    tactile: bool = True  # tactile inputs and outputs (7.2.10)
    memory: bool = True  # recurrent denoising with reservoir activations (7.2.8)
    recurrent: bool = False  # recurrent branch (7.2.6) trained on trajectories (7.2.7)
    denoise: bool = True  # 7.2.2
    masks: bool = True  # masked inputs/losses, masks predicted (7.2.5)
    follow_unobserved: bool = True  # inference: unobserved points move rigidly with their body's seen points
    velocity_input: bool = False  # current velocities as inputs; off measured better (docs/policy.md)
    phase_input: bool = False  # seconds since the episode start as an input (a clock for the phase)
    rigid_objects: bool = False  # inference: object keypoint velocities projected onto rigid motions
    pair_outputs: bool = True  # pairwise translation outputs and constraint (7.8)
    dynamics: bool = True  # object dynamics J_D, plausibility loss, constraint (7.13-7.15)
    body_dynamics: bool = False  # J_D shared by the points of one rigid object (trained where any of them is seen)
    tactile_model: bool = False  # 7.2.9 model-based tactile
    object_model: bool = False  # 7.2.9 object-state model
    rotate: bool = True  # 7.2.4: random rotations about gravity (ignored where canonical_frame)
    canonical_frame: bool = False  # 7.2.4 exactly: the net sees the scene turned so the reference object has yaw 0
    mirror: bool = True  # 7.6.8
    left_probability: float = 0.6  # 7.6.8
    noise_base: float = 10.0  # b_n
    noise_exponent: tuple[float, float] = (-3.3, -1.2)  # R_U: 0.5 mm .. 6 cm
    noise_gain: float = 8.0  # f_n (1/s): fraction of a displacement corrected per second
    correction_speed: float = 0.0  # m/s; > 0: small displacements are corrected at least this fast (gain up to 1/dt)
    rigid_noise: float = 1.0  # per-body translation noise, relative to the per-point noise
    object_noise: float = 0.5  # object noise relative to hand noise
    lag_noise: float = 0.0  # probability that a sample's noise is the scene lagging behind: positions of up to
    lag_s: float = 0.3  # this many seconds earlier (as a robot trails its plan), corrected like other noise
    goal_relative: bool = False  # denoising: a displaced object the hand acts on next moves the hand's target along
    noise_loss_ref: float = 0.0  # m; > 0 weighs each sample's velocity loss by ref / (ref + noise scale)
    reservoir: int = 32
    reservoir_radius: float = 0.98
    reservoir_periods: tuple[float, float] = (0.0, 0.0)  # s; > 0: W_R turns with these periods (log-spaced)
    reservoir_seed: int = -1  # >= 0: the reservoir's own seed, apart from the weights' and samples' (-1: init_seed)
    w_dH_loss: float = 1.0  # loss weight of the reservoir rate output (7.10 drives the memory at inference)
    reservoir_noise: float = 20.0  # reservoir input noise per metre of position noise (in H std units)
    hidden: tuple[int, ...] = (2048, 512, 512, 512)
    rec_in: int = 32
    rec_hidden: int = 16
    dropout: float = 0.2
    seq_len: int = 64  # recurrent training window
    reset_probability: float = 0.05  # recurrent training: reset positions to the demonstration
    w_pair: float = 0.0  # weight of the 7.8 pair constraint at inference; 1.0 measured worse (docs/policy.md)
    w_dyn: float = 3.0  # weight of J_D V_pinch against the net's object velocity (7.15); 1.0 let the board drift
    w_memory_prior: float = 0.01  # weight of 7.9 (H = H_P) against 7.10 (H = H_prev + dH_P dt); 1.0 measured worse
    w_plausible: float = 1e-3
    pair_eps: float = 0.0025  # m^2 (5 cm): the bias of the 7.8 normalization
    pair_input_eps: float = 0.0  # m^2; > 0 feeds pairs as P / (|P|^2 + eps) (7.8's form) instead of raw P
    turns: int = 1  # inference: outputs averaged over this many turns of the scene about gravity ...
    turn_spread: float = 0.5  # ... spread evenly over +-this (rad); the whole circle measured worse (docs/policy.md)
    max_speed: float = 1.5  # m/s, bound applied before the consistency solve
    steps: int = 8000  # the validation rollout still improved at 4000 (docs/policy.md)
    batch: int = 256
    lr: float = 1e-3
    ema: float = 0.0  # > 0: decay of a moving average of the weights, which is scored and kept (presets: 0.999)
    eval_every: int = 500
    eval_from: float = 0.5  # first selection rollout at this fraction of the steps (best came at 7500 of 8000)
    seed: int = 0
    candidates: int = 1  # > 1: this many draws are trained for candidate_fraction of the steps, and the one
    candidate_fraction: float = 1.0  # whose selection rollouts then score best is kept (and trained on to the end)
    candidate: int = 0  # which of the draws this is (set on the kept net's config)

    def __post_init__(self) -> None:
        if self.candidates < 1 or not 0 < self.candidate_fraction <= 1 or not 0 <= self.candidate < self.candidates:
            raise ValueError(f"candidates must be at least 1 and candidate_fraction in (0, 1], not "
                             f"{self.candidates} and {self.candidate_fraction} (candidate {self.candidate})")

    @property
    def init_seed(self) -> int:
        """Seed of the initial weights, the reservoir and the sample order: one per candidate draw."""
        return self.seed * self.candidates + self.candidate

    @property
    def candidate_steps(self) -> int:
        return min(max(1, round(self.candidate_fraction * self.steps)), self.steps)

    def to_json(self) -> str:
        return json.dumps(asdict(self))

    @classmethod
    def from_json(cls, text: str) -> PolicyConfig:
        known = {f.name for f in fields(cls)}  # fields of older or newer versions are left out
        return cls(**{k: tuple(v) if isinstance(v, list) else v  # JSON has no tuples
                      for k, v in json.loads(text).items() if k in known})

    def replace(self, **changes) -> PolicyConfig:
        return type(self)(**{**asdict(self), **changes})


# Since session 24 the reservoir turns with fixed periods and a quarter of the denoising noise is the
# scene lagging behind: steadier over training draws open loop, and with catch-up hand feedback
# (`xm eval --execute`, --catch-mm 30) 67 / 72 in the robot loop (docs/policy.md, Session 24)
_STEADY = {"reservoir_periods": (0.25, 8.0), "lag_noise": 0.25}
PRESETS: dict[str, PolicyConfig] = {
    "multimodal": PolicyConfig(body_dynamics=True, ema=0.999, **_STEADY),
    "no_tactile": PolicyConfig(name="no_tactile", tactile=False, body_dynamics=True, ema=0.999, **_STEADY),
    "single_state": PolicyConfig(name="single_state", tactile=False, memory=False, body_dynamics=True, ema=0.999,
                                 lag_noise=_STEADY["lag_noise"]),  # no reservoir to fix
}


def preset(name: str, **changes) -> PolicyConfig:
    if name not in PRESETS:
        raise KeyError(f"unknown preset {name!r}; known: {', '.join(PRESETS)}")
    return PRESETS[name].replace(**changes)


def config_changes(items: list[str]) -> dict:
    """``KEY=VALUE`` strings (the CLIs' ``--set``) as PolicyConfig changes, each typed like its field;
    tuples are comma-separated. ValueError names the bad item."""
    defaults = asdict(PolicyConfig())
    changes: dict = {}
    for item in items:
        key, sep, value = (part.strip() for part in item.partition("="))
        if not sep or key not in defaults or key == "name":
            raise ValueError(f"--set {item!r}: expected KEY=VALUE with KEY a PolicyConfig field "
                             f"({', '.join(k for k in defaults if k != 'name')})")
        current = defaults[key]
        try:
            if isinstance(current, bool):
                if value.lower() not in ("true", "false", "1", "0"):
                    raise ValueError
                changes[key] = value.lower() in ("true", "1")
            elif isinstance(current, (tuple, list)):
                changes[key] = tuple(type(current[0])(v) for v in value.split(","))
            else:
                changes[key] = type(current)(value)
        except ValueError:
            raise ValueError(f"--set {key}={value!r}: not a {type(current).__name__} like the default "
                             f"{current!r}") from None
    try:
        PolicyConfig(**changes)
    except ValueError as exc:
        raise ValueError(f"--set: {exc}") from None
    return changes


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
    """Features -> trunk -> all outputs; plus the optional recurrent branch and side models."""

    def __init__(self, cfg: PolicyConfig, K: int) -> None:
        super().__init__()
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
        n_in = n_geo + (2 * 2 * REGIONS if cfg.tactile else 0) + (cfg.reservoir if cfg.memory else 0)
        n_in += lay.K * 3 if cfg.object_model else 0
        n_in += 1 if cfg.phase_input else 0
        self.n_geo, self.n_in = n_geo, n_in
        self.register_buffer("mean", torch.zeros(n_in))
        self.register_buffer("std", torch.ones(n_in))
        self.register_buffer("H_mean", torch.zeros(max(cfg.reservoir, 1)))
        self.register_buffer("H_std", torch.ones(max(cfg.reservoir, 1)))
        self.register_buffer("dH_std", torch.ones(max(cfg.reservoir, 1)))
        self.register_buffer("H0", torch.zeros(max(cfg.reservoir, 1)))
        trunk_in = n_in + (cfg.rec_hidden if cfg.recurrent else 0)
        self.trunk = _mlp([trunk_in, *cfg.hidden], nn.ReLU, last_act=True)
        self.slices: dict[str, slice] = {}
        width = 0
        for key, n, on in (("vel", lay.P * 3, True), ("mask", lay.P, cfg.masks), ("tactile", 2 * REGIONS, cfg.tactile),
                           ("H", cfg.reservoir, cfg.memory), ("dH", cfg.reservoir, cfg.memory),
                           ("pairs", lay.pairs * 3, cfg.pair_outputs), ("J", lay.K * 2, cfg.dynamics)):
            if on:
                self.slices[key] = slice(width, width + n)
                width += n
        self.head = nn.Linear(cfg.hidden[-1], width)
        if cfg.recurrent:  # 7.2.6: bottleneck branch with dropout, fed the concatenation layer
            self.rec = nn.Sequential(nn.Linear(trunk_in, cfg.rec_in), nn.ReLU(), nn.Dropout(cfg.dropout),
                                     nn.Linear(cfg.rec_in, cfg.rec_hidden), nn.ReLU(),
                                     nn.Linear(cfg.rec_hidden, cfg.rec_hidden), nn.Tanh())
        if cfg.tactile_model:
            self.tactile_net = _mlp([n_geo, 64, 64, 64, 2 * REGIONS], nn.Tanh)
        if cfg.object_model:
            self.object_net = _mlp([n_geo, 32, 32, 32, lay.K * 3], nn.Tanh)

    # --- inputs ------------------------------------------------------------------------------
    def geometry(self, pos: torch.Tensor, vel: torch.Tensor, mask: torch.Tensor, vmask: torch.Tensor
                 ) -> tuple[torch.Tensor, torch.Tensor]:
        """Raw geometric features and their masks. pos, vel (B,P,3); mask, vmask (B,P) float."""
        B = pos.shape[0]
        hands = pos[:, :HAND_POINTS].reshape(B, 2, KEYPOINTS_PER_HAND, 3)
        local = (hands - hands[:, :, :1]).reshape(B, -1)
        a = pos[:, self.anchors]
        pairs = a[:, self.pj] - a[:, self.pi]
        eps = self.cfg.pair_input_eps
        if eps > 0:  # 7.8's normalization on the inputs: fine resolution near contact, far pairs compressed
            pairs = pairs * (eps ** 0.5 / POS_SCALE) / ((pairs ** 2).sum(-1, keepdim=True) + eps)
        pairs = pairs.reshape(B, -1)
        feats = torch.cat([torch.cat([local, pairs, a[:, :, 2]], dim=1) * POS_SCALE, vel.reshape(B, -1) * VEL_SCALE,
                           mask], dim=1)
        fmask = torch.cat([mask[:, self.m_local] * mask[:, self.m_wrist], mask[:, self.m_pi] * mask[:, self.m_pj],
                           mask[:, self.anchors], vmask[:, self.m_vel] * float(self.cfg.velocity_input),
                           torch.ones_like(mask)], dim=1)
        return feats, fmask

    def inputs(self, pos: torch.Tensor, vel: torch.Tensor, mask: torch.Tensor, vmask: torch.Tensor,
               tactile: torch.Tensor | None = None, tmask: torch.Tensor | None = None,
               H: torch.Tensor | None = None, phase: torch.Tensor | None = None
               ) -> tuple[torch.Tensor, torch.Tensor, dict]:
        """Normalized, masked input vector (B, n_in), the raw geometry, and side-model outputs."""
        cfg = self.cfg
        geo, gmask = self.geometry(pos, vel, mask, vmask)
        parts, masks, side = [geo], [gmask], {}
        if cfg.tactile:
            if cfg.tactile_model:  # 7.2.9: model tactile mixed in equal parts with the measurement
                side["tactile"] = self.tactile_net(((geo - self.mean[:self.n_geo]) / self.std[:self.n_geo]) * gmask)
                t_in = 0.5 * tactile.reshape(len(geo), -1) * TACTILE_SCALE + 0.5 * side["tactile"].detach()
            else:
                t_in = tactile.reshape(len(geo), -1) * TACTILE_SCALE
            tm = tmask.reshape(len(geo), -1)
            parts += [t_in, tm]
            masks += [tm, torch.ones_like(tm)]
        if cfg.memory:
            parts.append(H)
            masks.append(torch.ones_like(H))
        if cfg.object_model:
            side["objects"] = self.object_net(((geo - self.mean[:self.n_geo]) / self.std[:self.n_geo]) * gmask)
            parts.append(side["objects"].detach())
            masks.append(torch.ones_like(side["objects"]))
        if cfg.phase_input:
            parts.append(phase.reshape(-1, 1))
            masks.append(torch.ones_like(parts[-1]))
        x = torch.cat(parts, dim=1)
        return (x - self.mean) / self.std * torch.cat(masks, dim=1), geo, side

    def forward(self, x: torch.Tensor, rec: torch.Tensor | None = None
                ) -> tuple[dict[str, torch.Tensor], torch.Tensor | None]:
        if self.cfg.recurrent:
            x = torch.cat([x, rec], dim=1)
        out = self.head(self.trunk(x))
        res = {k: out[:, s] for k, s in self.slices.items()}
        return res, (self.rec(x) if self.cfg.recurrent else None)

    def set_statistics(self, x: torch.Tensor) -> None:
        self.mean.copy_(x.mean(0))
        self.std.copy_(x.std(0).clamp_min(1e-2))
