"""The learning method of thesis chapter 7 behind the common method interface (fit / rollout).

``Ours(recipe)`` trains a ``services.policy.model.Policy`` from a ``Recipe`` (or a preset name:
"multimodal" = Table 7.1 row 1, "no_tactile" = row 2, "single_state" = row 3, "time_window" =
row 4). Training samples
(7.2.2): positions corrupted by exponentially scaled noise (7.6), the same noise times f_n
subtracted from the target velocities (7.7); reservoir activations corrupted alike and denoised
(7.9-7.10). Rollouts run the trained policy's compiled loop, as the node does.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from learning import dataset as D
from learning.presets import Recipe, preset
from learning.reservoir import Reservoir
from learning.train import TrainResult, fit_model
from services.policy.model import Policy, PolicyError
from services.policy.network import PAIR_SCALE, TACTILE_SCALE, VEL_SCALE, PolicyNet
from shared.demo import KEYPOINTS_PER_HAND, Demo


def _t(x: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(x, dtype=np.float32))


def goal_shift(R: np.ndarray, goal: np.ndarray, body: np.ndarray) -> np.ndarray:
    """(n,P,3): the displacement each hand's denoising target moves along with, zero elsewhere.
    ``R`` (n,P,3) the sample's noise, ``goal`` (n,2) the object body each hand acts on next
    (dataset.goal_bodies, -1 none), ``body`` (P,) body per point (hands 0, 1, objects from 2).
    The object noise stands for a new layout: a hand heading for a displaced object is to meet it
    where it is seen, so its target moves with that object's mean noise."""
    n = len(R)
    n_obj_bodies = int(body.max()) - 1
    shift = np.zeros_like(R)
    means = np.stack([R[:, body == 2 + g].mean(1) for g in range(n_obj_bodies)] + [np.zeros((n, 3))], axis=1)
    for h in range(2):
        shift[:, body == h] = means[np.arange(n), goal[:, h]][:, None]  # goal -1 picks the zero row
    return shift


class Ours:
    """Methods (1)-(4) of Table 7.1 and every switch of its recipe."""

    def __init__(self, recipe: Recipe | str = "multimodal") -> None:
        self.recipe = preset(recipe) if isinstance(recipe, str) else recipe
        self.name = self.recipe.name
        self.policy: Policy | None = None
        self.reservoir: Reservoir | None = None
        self.losses: list[float] = []
        self.train_seconds = 0.0

    @property
    def net(self) -> PolicyNet | None:
        return None if self.policy is None else self.policy.net

    # --- setup --------------------------------------------------------------------------------
    def setup(self, train: list[Demo]) -> D.StepData:
        """Builds the network, reservoir and statistics from the training demonstrations."""
        if not train:
            raise PolicyError("no training demonstrations")
        m, tc = self.recipe.model, self.recipe.train
        dt = float(train[0].dt)
        torch.manual_seed(tc.seed)
        net = PolicyNet(m, train[0].objects.shape[1])
        self.policy = Policy(net, self.recipe.inference, dt, list(train[0].object_names), self.recipe.name,
                             json.loads(self.recipe.to_json()))
        self.body = self.policy.body
        self._pool = _t(self.policy.pool_matrix())
        P = net.layout.P
        periods = tuple(t / dt for t in m.reservoir_periods) if min(m.reservoir_periods) > 0 else None
        self.reservoir = Reservoir(P, m.reservoir, m.reservoir_radius, tc.seed, periods) if m.memory else None
        if self.reservoir is not None:  # saved beside the weights: what the memory inputs were made of
            self.policy.extra_tensors = {"reservoir.W_R": torch.from_numpy(self.reservoir.W_R),
                                         "reservoir.W_I": torch.from_numpy(self.reservoir.W_I)}
        arrays = [D.demo_arrays(d) for d in D.augmented(train, tc.mirror)]
        data = D.step_data(arrays, self.reservoir, tc.left_probability, m.window)
        if m.memory:
            rng = np.random.default_rng(tc.seed + 1)
            angle = rng.uniform(0, 2 * np.pi, len(data)) if tc.rotate else 0.0
            Hs = Reservoir.rotated(data.H, angle)
            net.H_mean.copy_(_t(Hs.mean(0)))
            net.H_std.copy_(_t(Hs.std(0) + 1e-6))
            dH = (data.next_H[0] - data.H[0]) / dt
            net.dH_std.copy_(_t(np.sqrt((dH ** 2).mean(0)) + 1e-6))
            starts = data.step_index == 0
            net.H0.copy_(_t(Reservoir.rotated(data.H[:, starts], 0.0).mean(0)))
        rng = np.random.default_rng(tc.seed + 2)
        with torch.no_grad():
            x = self.batch_inputs(self.make_batch(data, rng, 2048, noise=False))
        net.set_statistics(x)
        return data

    # --- training samples ---------------------------------------------------------------------
    def make_batch(self, data: D.StepData, rng: np.random.Generator, n: int, noise: bool = True) -> dict:
        """A numpy batch with the denoising corruption (7.6-7.7) applied."""
        tc = self.recipe.train
        b = D.sample_batch(data, rng, n, tc.rotate)
        P = b["pos"].shape[1]
        scale = np.zeros(n)
        if tc.denoise and noise:
            scale = tc.noise_base ** rng.uniform(*tc.noise_exponent, n)
            bodies = rng.normal(0, 1, (n, self.body.max() + 1, 3))[:, self.body]
            z = rng.normal(0, 1, (n, P, 3)) + tc.rigid_noise * bodies
            z /= np.sqrt(1 + tc.rigid_noise ** 2)
            z[:, 2 * KEYPOINTS_PER_HAND:] *= tc.object_noise
            R = z * scale[:, None, None]
            if tc.lag_noise > 0:
                R = self.lag_displacement(data, b, rng, R)
        else:
            R = np.zeros_like(b["pos"])
        gain = self.correction_gain(data.dt)
        b["clean_pos"] = b["pos"]
        b["pos"] = b["pos"] + R  # 7.6
        b["target_vel"] = b["next_vel"] - R * gain  # 7.7
        if tc.goal_relative and "goal" in b:
            b["target_vel"] += goal_shift(R, b["goal"], self.body) * gain
        b["scale"] = scale
        if self.recipe.model.memory:
            net = self.net
            Hn = (b["H"] - net.H_mean.numpy()) / net.H_std.numpy()
            b["H_clean"], b["dH"] = Hn, (b["next_H"] - b["H"]) / data.dt / net.dH_std.numpy()
            b["H_in"] = Hn + rng.normal(0, 1, Hn.shape) * (scale * tc.reservoir_noise)[:, None]
        return b

    def lag_displacement(self, data: D.StepData, b: dict, rng: np.random.Generator, R: np.ndarray) -> np.ndarray:
        """``R`` with a ``lag_noise`` share of the samples' noise replaced by the scene's displacement
        back to up to ``lag_s`` earlier in its demonstration (turned with the sample)."""
        tc = self.recipe.train
        n = len(R)
        lag = np.minimum(rng.integers(1, max(2, round(tc.lag_s / data.dt) + 1), n), data.step_index[b["index"]])
        use = (rng.random(n) < tc.lag_noise) & (lag > 0)
        if not use.any():
            return R
        idx = b["index"][use]
        earlier = D.rotate_z(data.pos[idx - lag[use]] - data.pos[idx], b["angle"][use][:, None])
        earlier[~(data.mask[idx - lag[use]] & data.mask[idx])] = 0.0  # unseen then or now: no known lag
        R = R.copy()
        R[use] = earlier
        return R

    def correction_gain(self, dt: float) -> float:
        """The gain of the denoising target (7.7): f_n, at most 1/dt (a displacement corrected within a step)."""
        return min(self.recipe.train.noise_gain, 1.0 / dt)

    def batch_inputs(self, b: dict) -> torch.Tensor:
        mask = b["mask"] if self.recipe.model.masks else np.ones_like(b["mask"])
        window = wmask = None
        if "window" in b:
            window = _t(b["window"])
            wmask = _t(b["wmask"] if self.recipe.model.masks else np.ones_like(b["wmask"]))
        return self.net.inputs(_t(b["pos"]), _t(b["vel"]), _t(mask), _t(b["tactile"]), _t(b["tmask"]),
                               _t(b["H_in"]) if "H_in" in b else None, window, wmask)

    def loss(self, b: dict) -> tuple[torch.Tensor, dict[str, float]]:
        """Masked losses of every active output for one batch (denoising targets)."""
        m, tc, net = self.recipe.model, self.recipe.train, self.net
        out = net(self.batch_inputs(b))
        n, P = b["pos"].shape[:2]
        wv = _t(np.repeat(b["next_vmask"], 3, axis=1).reshape(n, P * 3)) if m.masks else torch.ones(n, P * 3)
        tv = _t(b["target_vel"].reshape(n, -1) * VEL_SCALE)
        parts = {"vel": ((out["vel"] - tv) ** 2 * wv).sum() / wv.sum().clamp_min(1)}
        if m.masks:
            parts["mask"] = 0.1 * torch.nn.functional.binary_cross_entropy_with_logits(out["mask"], _t(b["next_mask"]))
        if m.tactile:
            tm = _t(b["tmask"].reshape(n, -1))
            tt = _t(b["next_tactile"].reshape(n, -1) * TACTILE_SCALE)
            parts["tactile"] = ((out["tactile"] - tt) ** 2 * tm).sum() / tm.sum().clamp_min(1)
        if m.memory:
            parts["H"] = ((out["H"] - _t(b["H_clean"])) ** 2).mean()
            parts["dH"] = tc.w_dH_loss * ((out["dH"] - _t(b["dH"])) ** 2).mean()
        lay = net.layout
        if m.pair_outputs:
            nxt = b["pos"] + b["target_vel"] * self.policy.dt
            a_now, a_next = b["pos"][:, lay.anchors], nxt[:, lay.anchors]
            tgt = (a_next[:, lay.pair_j] - a_next[:, lay.pair_i]) - (a_now[:, lay.pair_j] - a_now[:, lay.pair_i])
            d2 = (a_next[:, lay.pair_j] - a_next[:, lay.pair_i]) ** 2
            w = tc.pair_eps / (d2.sum(-1, keepdims=True) + tc.pair_eps)  # 7.8 normalization, 1 at contact
            am = b["next_mask"][:, lay.anchors]
            pm = (am[:, lay.pair_j] & am[:, lay.pair_i]).astype(float)[..., None] if m.masks else 1.0
            res = (out["pairs"].reshape(n, -1, 3) - _t(tgt * PAIR_SCALE)) * _t(w * pm)
            parts["pairs"] = (res ** 2).mean() * 3
        if m.dynamics:
            parts["dyn"], parts["plausible"] = self.dynamics_loss(b, out["J"].reshape(n, lay.K, 2))
        total = sum(parts.values())
        return total, {k: float(v.detach()) for k, v in parts.items()}

    def dynamics_loss(self, b: dict, J: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """7.14 on the clean input velocities, and the plausibility loss of J_D against the touch."""
        m, lay = self.recipe.model, self.net.layout
        n = len(J)
        if m.body_dynamics:
            J = torch.einsum("kj,njh->nkh", self._pool, J)
        v = b["vel"] * VEL_SCALE
        vo = _t(v[:, 2 * KEYPOINTS_PER_HAND:])
        if m.body_dynamics:
            # a hand holding an object hides its own thumb and index: where they are not both seen,
            # its seen points' mean velocity stands in for the pinch's (else no sample where an
            # object moves would train J_D)
            hv = v[:, :2 * KEYPOINTS_PER_HAND].reshape(n, 2, KEYPOINTS_PER_HAND, 3)
            hm = b["vmask"][:, :2 * KEYPOINTS_PER_HAND].reshape(n, 2, KEYPOINTS_PER_HAND)
            pinch_seen = b["vmask"][:, lay.pinch].all(axis=2)  # (n,2)
            seen_mean = (hv * hm[..., None]).sum(2) / np.maximum(hm.sum(2), 1)[..., None]
            vp = _t(np.where(pinch_seen[..., None], v[:, lay.pinch].mean(axis=2), seen_mean))
            ok = b["vmask"][:, 2 * KEYPOINTS_PER_HAND:] & hm.any(2).all(1)[:, None]
        else:
            vp = _t(v[:, lay.pinch].mean(axis=2))  # (n,2,3)
            ok = b["vmask"][:, 2 * KEYPOINTS_PER_HAND:] & b["vmask"][:, lay.pinch].all(axis=(1, 2))[:, None]
        okt = _t(ok.astype(float))[..., None]
        dyn = ((torch.einsum("nkh,nhd->nkd", J, vp) - vo) ** 2 * okt).sum() / okt.sum().clamp_min(1)
        force = b["tactile"].sum(-1) * TACTILE_SCALE  # (n,2)
        gloved = _t(b["tmask"].any(-1).astype(float))
        inv = gloved / (_t(force) + 0.1)
        return dyn, self.recipe.train.w_plausible * ((J * inv[:, None, :]) ** 2).mean()

    # --- method interface ---------------------------------------------------------------------
    def fit(self, train: list[Demo], progress: bool = True) -> None:
        """Trains on ``train`` and keeps the final (averaged) weights; no validation data is used here."""
        fit_model(self, train, None, progress=progress)

    def rollout(self, start: Demo, steps: int) -> tuple[np.ndarray, np.ndarray]:
        if self.policy is None:
            raise PolicyError("fit() first")
        return self.policy.rollout(start, steps)

    def weights_updated(self) -> None:
        self.policy.weights_updated()

    def save(self, path: str) -> None:
        self.policy.save(path)


def train(recipe: Recipe | str, train_demos: list[Demo], val_demos: list[Demo] | None, out_dir: str | Path | None,
          progress: bool = True, on_progress: Callable[[dict], None] | None = None) -> TrainResult:
    """Trains a fresh policy: best on ``val_demos``, else the final weights. Writes the checkpoint and
    the training demonstrations (the node's naive fallback replays them) into ``out_dir``;
    ``on_progress``: see learning.train.fit_model."""
    method = Ours(recipe)
    result = fit_model(method, train_demos, val_demos, progress, Path(out_dir) if out_dir else None, on_progress)
    result.method = method
    return result
