"""The learning method of thesis chapter 7 behind the common Method interface (fit / rollout).

``Ours(config)`` builds ``network.PolicyNet`` from a ``PolicyConfig`` (or a preset name:
"multimodal" = Table 7.1 row 1, "no_tactile" = row 2, "single_state" = row 3). Training samples
(7.2.2): positions corrupted by exponentially scaled noise (7.6), the same noise times f_n
subtracted from the target velocities (7.7); reservoir activations corrupted alike and denoised
(7.9-7.10). Inference: one network evaluation, then the consistency solve (consistency.py).
"""

from __future__ import annotations

import numpy as np
import torch

from services.policy import compiled as C
from services.policy import dataset as D
from services.policy.consistency import ConsistencySolver, follow_bodies, rigid_velocities
from services.policy.folded import FoldedNet, foldable
from services.policy.network import (
    PAIR_SCALE,
    PRESETS,
    TACTILE_SCALE,
    VEL_SCALE,
    PolicyConfig,
    PolicyNet,
    preset,
)
from services.policy.reservoir import Reservoir
from shared.demo import KEYPOINTS_PER_HAND, Demo

MAX_TACTILE_KPA = 500.0  # above any glove reading: bounds the tactile feedback of an untrained net
__all__ = ["PRESETS", "Ours", "PolicyConfig", "PolicyError", "preset"]


class PolicyError(RuntimeError):
    """The policy produced something that must not be used (NaN), or was used out of order."""


def _t(x: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(x, dtype=np.float32))


class Ours:
    """Method (1)-(3) of Table 7.1 and every ablation switch of PolicyConfig."""

    def __init__(self, config: PolicyConfig | str = "multimodal") -> None:
        self.cfg = preset(config) if isinstance(config, str) else config
        self.name = self.cfg.name
        self.net: PolicyNet | None = None
        self.reservoir: Reservoir | None = None
        self.losses: list[float] = []
        self.train_seconds = 0.0
        self.candidate_scores: list[dict] = []  # each training draw's selection scores (cfg.candidates > 1)
        self.K, self.dt, self.object_names = 0, 0.02, []
        self.fold_inference = True  # batch-one inference through folded() (P4); False: plain PolicyNet
        self.compile_inference = True  # steps and rollouts through compiled() (P4); False: the Python step
        self._folded: FoldedNet | None = None
        self._folded_net: PolicyNet | None = None
        self._folded_tensors: list[torch.Tensor] = []
        self._folded_stamp: tuple = ()
        self._compiled: C.CompiledRollout | None = None
        self.frame_idx, self.frame_ref = np.zeros(0, int), np.zeros((0, 2))  # canonical frame (setup)
        self._pool, self._pool_names = np.zeros((0, 0)), None  # body_pooled's averaging matrix and its names

    def sibling(self, config: PolicyConfig) -> Ours:
        """A fresh, untrained instance with this one's inference switches (another training draw)."""
        other = type(self)(config)
        other.fold_inference, other.compile_inference = self.fold_inference, self.compile_inference
        return other

    def adopt(self, other: Ours) -> None:
        """Takes over another instance's whole state: the training draw that was kept."""
        self.__dict__.update(other.__dict__)

    # --- setup --------------------------------------------------------------------------------
    def setup(self, train: list[Demo]) -> D.StepData:
        """Builds the network, reservoir and statistics from the training demonstrations."""
        if not train:
            raise PolicyError("no training demonstrations")
        cfg = self.cfg
        self.K, self.dt, self.object_names = train[0].objects.shape[1], float(train[0].dt), list(train[0].object_names)
        torch.manual_seed(cfg.init_seed)
        self.net = PolicyNet(cfg, self.K)
        P = self.net.layout.P
        periods = tuple(t / self.dt for t in cfg.reservoir_periods) if min(cfg.reservoir_periods) > 0 else None
        reservoir_seed = cfg.init_seed if cfg.reservoir_seed < 0 else cfg.reservoir_seed
        self.reservoir = (Reservoir(P, cfg.reservoir, cfg.reservoir_radius, reservoir_seed, periods)
                          if cfg.memory else None)
        arrays = [D.demo_arrays(d) for d in D.augmented(train, cfg.mirror)]
        data = D.step_data(arrays, self.reservoir, cfg.left_probability)
        self.body = self.bodies()
        if cfg.canonical_frame:
            idx, self.frame_ref = D.reference_object(self.object_names, train[0].objects[0].astype(np.float64))
            self.frame_idx = idx + 2 * KEYPOINTS_PER_HAND
        if cfg.memory:
            rng = np.random.default_rng(cfg.init_seed + 1)
            if cfg.canonical_frame:
                angle = -self.yaw(data.pos)
            else:
                angle = rng.uniform(0, 2 * np.pi, len(data)) if cfg.rotate else 0.0
            Hs = Reservoir.rotated(data.H, angle)
            self.net.H_mean.copy_(_t(Hs.mean(0)))
            self.net.H_std.copy_(_t(Hs.std(0) + 1e-6))
            dH = (data.next_H[0] - data.H[0]) / self.dt
            self.net.dH_std.copy_(_t(np.sqrt((dH ** 2).mean(0)) + 1e-6))
            starts = data.step_index == 0
            a0 = angle[starts] if cfg.canonical_frame else 0.0
            self.net.H0.copy_(_t(Reservoir.rotated(data.H[:, starts], a0).mean(0)))
        rng = np.random.default_rng(cfg.init_seed + 2)
        with torch.no_grad():
            x = self.batch_inputs(self.make_batch(data, rng, 2048, noise=False))[0]
        self.net.set_statistics(x)
        return data

    def yaw(self, pos: np.ndarray) -> np.ndarray:
        """Yaw of the reference object in positions (..., P, 3): the canonical frame's turn."""
        return D.frame_yaw(pos[..., self.frame_idx, :], self.frame_ref)

    def bodies(self) -> np.ndarray:
        """Rigid body per point: 0 and 1 the hands, then one per object."""
        return np.concatenate([np.repeat([0, 1], KEYPOINTS_PER_HAND), 2 + D.object_groups(self.object_names)])

    def solver(self, dt: float | None = None) -> ConsistencySolver:
        """The inference solve; ``dt`` (default the sample period) is the step it integrates over:
        a horizon may be rolled out at the trajectory optimizer's knot spacing instead (7.16: the
        rollout's steps are the optimizer's keyframes)."""
        c = self.cfg
        return ConsistencySolver(self.net.layout, dt or self.dt, c.w_pair if c.pair_outputs else 0.0,
                                 c.w_dyn if c.dynamics else 0.0, c.pair_eps)

    # --- training samples ---------------------------------------------------------------------
    def make_batch(self, data: D.StepData, rng: np.random.Generator, n: int, noise: bool = True) -> dict:
        """A numpy batch with the denoising corruption (7.6-7.7) applied."""
        cfg = self.cfg
        b = D.sample_batch(data, rng, n, cfg.rotate and not cfg.canonical_frame)
        P = b["pos"].shape[1]
        scale = np.zeros(n)
        if cfg.denoise and noise:
            scale = cfg.noise_base ** rng.uniform(*cfg.noise_exponent, n)
            bodies = rng.normal(0, 1, (n, self.body.max() + 1, 3))[:, self.body]
            z = rng.normal(0, 1, (n, P, 3)) + cfg.rigid_noise * bodies
            z /= np.sqrt(1 + cfg.rigid_noise ** 2)
            z[:, 2 * KEYPOINTS_PER_HAND:] *= cfg.object_noise
            R = z * scale[:, None, None]
            if cfg.lag_noise > 0:
                R = self.lag_displacement(data, b, rng, R)
        else:
            R = np.zeros_like(b["pos"])
        gain = self.correction_gain(scale, data.dt)[:, None, None]
        b["clean_pos"] = b["pos"]
        b["pos"] = b["pos"] + R  # 7.6
        b["target_vel"] = b["next_vel"] - R * gain  # 7.7
        if cfg.goal_relative and "goal" in b:
            # the object noise stands for a new layout: each hand's target moves with the object it
            # acts on next (dataset.goal_bodies), so the hand learns to follow that object's position
            groups = D.object_groups(self.object_names)
            R_obj = R[:, 2 * KEYPOINTS_PER_HAND:]
            # (n, bodies + 1, 3): each body's mean noise, then zero for goal -1 (no object)
            shift = np.stack([R_obj[:, groups == g].mean(1) for g in range(groups.max() + 1 if len(groups) else 0)]
                             + [np.zeros((n, 3))], axis=1)
            for h in range(2):
                pts = slice(h * KEYPOINTS_PER_HAND, (h + 1) * KEYPOINTS_PER_HAND)
                b["target_vel"][:, pts] += shift[np.arange(n), b["goal"][:, h]][:, None] * gain
        b["scale"] = scale
        if cfg.canonical_frame:  # turned as inference turns it: by the yaw seen in the noisy input
            back = -self.yaw(b["pos"])
            for key in ("pos", "clean_pos", "vel", "next_pos", "next_vel", "target_vel"):
                b[key] = D.rotate_z(b[key], back[:, None])
            if data.H is not None:
                from services.policy.reservoir import Reservoir

                b["H"] = Reservoir.rotated(data.H[:, b["index"]], back)
                b["next_H"] = Reservoir.rotated(data.next_H[:, b["index"]], back)
        if cfg.memory:
            Hn = (b["H"] - self.net.H_mean.numpy()) / self.net.H_std.numpy()
            nHn = (b["next_H"] - self.net.H_mean.numpy()) / self.net.H_std.numpy()
            b["H_clean"], b["dH"] = Hn, (b["next_H"] - b["H"]) / data.dt / self.net.dH_std.numpy()
            b["H_in"] = Hn + rng.normal(0, 1, Hn.shape) * (scale * cfg.reservoir_noise)[:, None]
            del nHn
        return b

    def lag_displacement(self, data: D.StepData, b: dict, rng: np.random.Generator, R: np.ndarray) -> np.ndarray:
        """``R`` with a ``lag_noise`` share of the samples' noise replaced by the scene's displacement
        back to up to ``lag_s`` earlier in its demonstration (turned with the sample)."""
        n = len(R)
        lag = np.minimum(rng.integers(1, max(2, round(self.cfg.lag_s / data.dt) + 1), n), data.step_index[b["index"]])
        use = (rng.random(n) < self.cfg.lag_noise) & (lag > 0)
        if not use.any():
            return R
        idx = b["index"][use]
        earlier = D.rotate_z(data.pos[idx - lag[use]] - data.pos[idx], b["angle"][use][:, None])
        earlier[~(data.mask[idx - lag[use]] & data.mask[idx])] = 0.0  # unseen then or now: no known lag
        R = R.copy()
        R[use] = earlier
        return R

    def body_pooled(self, J):
        """With ``body_dynamics``: each object point's J_D replaced by its body's mean, so that a
        point hidden in the hand (never seen moving, so never trained) moves like its seen ones."""
        if not self.cfg.body_dynamics:
            return J
        if self._pool_names != self.object_names:  # built once per object list
            groups = D.object_groups(self.object_names)
            A = (groups[:, None] == groups[None]).astype(np.float64)
            self._pool, self._pool_names = A / A.sum(1, keepdims=True), list(self.object_names)
        A = self._pool
        if isinstance(J, torch.Tensor):
            return torch.einsum("kj,njh->nkh", _t(A), J)
        return A @ J

    def correction_gain(self, scale: np.ndarray, dt: float) -> np.ndarray:
        """Per-sample gain of the denoising target (7.7): f_n, raised for small noise scales so that
        a displacement of ``scale`` is corrected at ``correction_speed`` or more (capped at 1/dt):
        near the demonstration the correction then still outruns the net's velocity bias."""
        cfg = self.cfg
        gain = np.full(len(scale), min(cfg.noise_gain, 1.0 / dt))
        if cfg.correction_speed > 0:
            gain = np.maximum(gain, np.minimum(cfg.correction_speed / np.maximum(scale, 1e-9), 1.0 / dt))
        return gain

    def batch_inputs(self, b: dict) -> tuple[torch.Tensor, torch.Tensor, dict]:
        mask = b["mask"] if self.cfg.masks else np.ones_like(b["mask"])
        vmask = b["vmask"] if self.cfg.masks else np.ones_like(b["vmask"])
        return self.net.inputs(_t(b["pos"]), _t(b["vel"]), _t(mask), _t(vmask), _t(b["tactile"]),
                               _t(b["tmask"]), _t(b["H_in"]) if "H_in" in b else None,
                               _t(b["phase"]) if self.cfg.phase_input else None)

    def loss(self, b: dict, rec: torch.Tensor | None = None) -> tuple[torch.Tensor, dict[str, float]]:
        """Masked losses of every active output for one batch (denoising targets)."""
        cfg, net = self.cfg, self.net
        x, _, side = self.batch_inputs(b)
        if cfg.recurrent and rec is None:
            rec = torch.zeros(len(x), cfg.rec_hidden)
        out, rec_next = net(x, rec)
        self.last = (out, rec_next)  # for the recurrent training loop
        n, P = b["pos"].shape[:2]
        wv = _t(np.repeat(b["next_vmask"], 3, axis=1).reshape(n, P * 3)) if cfg.masks else torch.ones(n, P * 3)
        if cfg.noise_loss_ref > 0:  # large-noise samples carry large, partly unpredictable targets
            wv = wv * _t(cfg.noise_loss_ref / (cfg.noise_loss_ref + b.get("scale", np.zeros(n))))[:, None]
        tv = _t(b["target_vel"].reshape(n, -1) * VEL_SCALE)
        parts = {"vel": ((out["vel"] - tv) ** 2 * wv).sum() / wv.sum().clamp_min(1)}
        if cfg.masks:
            parts["mask"] = 0.1 * torch.nn.functional.binary_cross_entropy_with_logits(out["mask"], _t(b["next_mask"]))
        if cfg.tactile:
            tm = _t(b["tmask"].reshape(n, -1))
            tt = _t(b["next_tactile"].reshape(n, -1) * TACTILE_SCALE)
            parts["tactile"] = ((out["tactile"] - tt) ** 2 * tm).sum() / tm.sum().clamp_min(1)
            if cfg.tactile_model:
                now = _t(b["tactile"].reshape(n, -1) * TACTILE_SCALE)
                parts["tactile_model"] = ((side["tactile"] - now) ** 2 * tm).sum() / tm.sum().clamp_min(1)
        if cfg.memory:
            parts["H"] = ((out["H"] - _t(b["H_clean"])) ** 2).mean()
            parts["dH"] = cfg.w_dH_loss * ((out["dH"] - _t(b["dH"])) ** 2).mean()
        lay = net.layout
        if cfg.pair_outputs:
            nxt = b["pos"] + b["target_vel"] * self.dt
            a_now, a_next = b["pos"][:, lay.anchors], nxt[:, lay.anchors]
            tgt = (a_next[:, lay.pair_j] - a_next[:, lay.pair_i]) - (a_now[:, lay.pair_j] - a_now[:, lay.pair_i])
            d2 = (a_next[:, lay.pair_j] - a_next[:, lay.pair_i]) ** 2
            w = cfg.pair_eps / (d2.sum(-1, keepdims=True) + cfg.pair_eps)  # 7.8 normalization, 1 at contact
            am = b["next_mask"][:, lay.anchors]
            pm = (am[:, lay.pair_j] & am[:, lay.pair_i]).astype(float)[..., None] if cfg.masks else 1.0
            res = (out["pairs"].reshape(n, -1, 3) - _t(tgt * PAIR_SCALE)) * _t(w * pm)
            parts["pairs"] = (res ** 2).mean() * 3
        if cfg.dynamics:  # 7.14 on the clean input velocities
            J = self.body_pooled(out["J"].reshape(n, self.K, 2))
            v = b["vel"] * VEL_SCALE
            vo = _t(v[:, 2 * KEYPOINTS_PER_HAND:])
            if cfg.body_dynamics:
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
            parts["dyn"] = ((torch.einsum("nkh,nhd->nkd", J, vp) - vo) ** 2 * okt).sum() / okt.sum().clamp_min(1)
            force = b["tactile"].sum(-1) * TACTILE_SCALE  # (n,2)
            gloved = _t(b["tmask"].any(-1).astype(float))
            inv = gloved / (_t(force) + 0.1)
            parts["plausible"] = cfg.w_plausible * ((J * inv[:, None, :]) ** 2).mean()
        if cfg.object_model:
            vo_next = _t(b["next_vel"][:, 2 * KEYPOINTS_PER_HAND:].reshape(n, -1) * VEL_SCALE)
            parts["object_model"] = ((side["objects"] - vo_next) ** 2).mean()
        total = sum(parts.values())
        return total, {k: float(v.detach()) for k, v in parts.items()}

    def sequence_loss(self, data: D.StepData, rng: np.random.Generator) -> tuple[torch.Tensor, dict[str, float]]:
        """Recurrent training (7.2.7) on windows of the demonstrations: predicted velocities are
        integrated and fed back as input positions, positions are reset to the demonstration at
        random frames, recurrent feedback is reset only at the window start (the demonstration
        start where the window begins there). One rotation angle per rollout (7.2.4). Gradients
        flow through the recurrent branch; the integrated positions enter as data."""
        cfg = self.cfg
        L, n = cfg.seq_len, max(4, cfg.batch // cfg.seq_len)
        ok = np.flatnonzero(data.step_index[:len(data) - L + 1] + L - 1
                            == data.step_index[L - 1:len(data)][:len(data) - L + 1]
                            ) if len(data) >= L else np.array([], int)
        if not len(ok):
            raise PolicyError(f"seq_len {L} is longer than every demonstration")
        p = data.prob[ok] / data.prob[ok].sum()
        rows = rng.choice(ok, n, p=p)[:, None] + np.arange(L)[None]  # (n, L)
        if cfg.canonical_frame:
            angle = -self.yaw(data.pos[rows[:, 0]])
        else:
            angle = rng.uniform(0, 2 * np.pi, n) if cfg.rotate else np.zeros(n)
        gain = min(cfg.noise_gain, 1.0 / data.dt)
        pos_sim, vel_sim, rec, total = None, None, None, 0.0
        parts: dict[str, float] = {}
        for t in range(L):
            r = rows[:, t]
            b = D.batch_at(data, r, angle)
            if pos_sim is None:
                pos_sim, vel_sim = b["pos"].copy(), b["vel"].copy()
            b["clean_pos"] = b["pos"]
            b["target_vel"] = b["next_vel"] + (b["pos"] - pos_sim) * gain  # back onto the demonstration
            b["pos"], b["vel"] = pos_sim, vel_sim
            if cfg.memory:
                Hn = (b["H"] - self.net.H_mean.numpy()) / self.net.H_std.numpy()
                b["H_clean"] = b["H_in"] = Hn
                b["dH"] = (b["next_H"] - b["H"]) / data.dt / self.net.dH_std.numpy()
            loss, p_t = self.loss(b, rec)
            total = total + loss / L
            for k, v in p_t.items():
                parts[k] = parts.get(k, 0.0) + v / L
            out, rec = self.last
            v = np.clip(out["vel"].detach().numpy().reshape(pos_sim.shape) / VEL_SCALE, -cfg.max_speed, cfg.max_speed)
            new = pos_sim + v * data.dt
            reset = rng.random(n) < cfg.reset_probability
            new[reset] = b["next_pos"][reset]
            vel_sim, pos_sim = (new - pos_sim) / data.dt, new
        return total, parts

    # --- Method interface ---------------------------------------------------------------------
    def fit(self, train: list[Demo], progress: bool = True) -> None:
        """Trains on ``train`` and keeps the final (averaged) weights; no validation data is used here."""
        from services.policy.train import fit_model

        fit_model(self, train, None, progress=progress)

    def initial_state(self, start: Demo) -> dict:
        if not np.isfinite(start.hands[0]).all() or not np.isfinite(start.objects[0]).all():
            raise PolicyError(f"start state of {start.meta.get('demo', '?')} has NaN keypoints")
        if start.objects.shape[1] != self.K:
            raise PolicyError(f"start state has {start.objects.shape[1]} object points; trained with {self.K}")
        pos = np.concatenate([start.hands[0].reshape(-1, 3), start.objects[0]]).astype(np.float64)
        mask = np.concatenate([start.hand_mask[0].reshape(-1), start.object_mask[0]]).astype(bool)
        state = {"pos": pos, "vel": np.zeros_like(pos), "mask": mask if self.cfg.masks else np.ones_like(mask),
                 "tactile": start.tactile[0].astype(np.float64), "tmask": start.tactile_mask[0].astype(bool)}
        if self.cfg.memory:
            state["H"] = ((self.net.H0 - self.net.H_mean) / self.net.H_std).numpy().astype(np.float64)
        if self.cfg.recurrent:
            state["rec"] = np.zeros(self.cfg.rec_hidden)
        return state

    def folded(self) -> FoldedNet | None:
        """The folded copy of the network for batch-one inference (folded.py), rebuilt whenever
        the weights or statistics changed since it was made; None where the config cannot fold."""
        if self.net is None or self.net.training or not foldable(self.net):
            return None
        if self._folded is None or self._folded_net is not self.net:
            self._folded_tensors = [*self.net.parameters(), *self.net.buffers()]
        stamp = tuple(t._version for t in self._folded_tensors)  # any in-place update (optimizer, loading) bumps it
        if self._folded is None or self._folded_net is not self.net or self._folded_stamp != stamp:
            keys = [k for k in self.net.slices if k != "pairs" or (self.cfg.w_pair > 0)]
            self._folded, self._folded_net, self._folded_stamp = FoldedNet(self.net, tuple(keys)), self.net, stamp
        return self._folded

    def compiled(self) -> C.CompiledRollout | None:
        """The compiled rollout loop (compiled.py) over the current folded net; None where the
        config, ``fold_inference`` or ``compile_inference`` rules it out."""
        if not (self.fold_inference and self.compile_inference) or not C.supports(self):
            return None
        fold = self.folded()
        if self._compiled is None or self._compiled.fold is not fold:
            self._compiled = C.CompiledRollout(self, fold, MAX_TACTILE_KPA)
        return self._compiled

    def roll(self, state: dict, steps: int, solver: ConsistencySolver | None = None,
             observed_objects: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``steps`` policy steps from ``state`` (which is not changed): positions (S,P,3), tactile
        (S,2,R) and memory (S,size) after each; ``observed_objects`` (S,K,3) as in ``step``. One
        compiled call where the config allows (P4), else ``step`` after ``step``; the same results
        either way."""
        solver = solver or self.solver()
        fast = self.compiled() if observed_objects is None else None
        if fast is not None:
            return self._roll_compiled(fast, state, steps, solver)[:3]
        pos = np.empty((steps, *np.shape(state["pos"])))
        tact = np.empty((steps, *np.shape(state["tactile"])))
        mem = np.empty((steps, len(state.get("H", []))))
        for t in range(steps):
            state = self.step(state, solver, None if observed_objects is None else observed_objects[t])
            pos[t], tact[t] = state["pos"], state["tactile"]
            if "H" in state:
                mem[t] = state["H"]
        return pos, tact, mem

    @staticmethod
    def _roll_compiled(fast: C.CompiledRollout, state: dict, steps: int, solver: ConsistencySolver
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        pos, tact, mem, mask, status = fast(state, steps, solver.dt, solver.w_dyn)
        if status == C.NET_NAN:
            raise PolicyError("network output contains NaN or inf")
        if status == C.POS_NAN:
            raise PolicyError("consistency solve produced NaN positions")
        return pos, tact, mem, mask

    def weights_updated(self) -> None:
        """The weights changed in a way their version counters do not show (a fused optimizer step):
        the folded copy is rebuilt on next use."""
        self._folded = None

    def network_outputs(self, state: dict, fold: bool | None = None) -> dict[str, np.ndarray]:
        """The forward pass of one state (no consistency solve): folded where the config allows
        (``fold_inference``); ``fold=False`` runs the plain PolicyNet (the reference the folded
        pass is tested and benchmarked against)."""
        if self.cfg.turns > 1 and fold is None:
            return self._turned_outputs(state)
        s = state
        vm = s["mask"] if self.cfg.masks else np.ones(len(s["mask"]), bool)
        fast = self.folded() if (self.fold_inference if fold is None else fold) else None
        if fast is not None:
            return fast(s["pos"], s["vel"], vm, vm, s["tactile"], s["tmask"], s.get("H"), s.get("t", 0.0))
        net = self.net
        with torch.inference_mode():
            vm = vm.astype(np.float32)
            x, _, _ = net.inputs(_t(s["pos"][None]), _t(s["vel"][None]), _t(vm[None]), _t(vm[None]),
                                 _t(s["tactile"][None]), _t(s["tmask"][None].astype(np.float32)),
                                 _t(s["H"][None]) if self.cfg.memory else None,
                                 _t(np.array([s.get("t", 0.0)])) if self.cfg.phase_input else None)
            out, rec = net(x, _t(s["rec"][None]) if self.cfg.recurrent else None)
        res = {k: v[0].numpy().astype(np.float64) for k, v in out.items()}
        if rec is not None:
            res["rec"] = rec[0].numpy().astype(np.float64)
        return res

    def turn_angles(self) -> np.ndarray:
        """The scene turns (rad about gravity) whose outputs are averaged at inference."""
        c = self.cfg
        return np.linspace(-c.turn_spread, c.turn_spread, c.turns) if c.turns > 1 else np.zeros(1)

    def _turned_outputs(self, state: dict) -> dict[str, np.ndarray]:
        """Test-time use of 7.2.4's augmentation: the net sees the state turned a few ways about
        gravity, its vector outputs are turned back and all outputs averaged. Folded, the turned
        copies go through as one batch (one matrix product per layer; on this CPU it costs about
        as much as one product per copy, docs/policy.md Session 9)."""
        angles = self.turn_angles()
        pos = D.rotate_z(np.broadcast_to(state["pos"], (len(angles), *state["pos"].shape)), angles[:, None])
        vel = D.rotate_z(np.broadcast_to(state["vel"], pos.shape), angles[:, None])
        fast = self.folded() if self.fold_inference else None
        if fast is not None:
            vm = state["mask"] if self.cfg.masks else np.ones(len(state["mask"]), bool)
            out = fast(pos, vel, vm, vm, state["tactile"], state["tmask"], state.get("H"), state.get("t", 0.0))
        else:
            each = [self.network_outputs(dict(state, pos=p, vel=v), fold=False) for p, v in zip(pos, vel, strict=True)]
            out = {k: np.stack([o[k] for o in each]) for k in each[0]}
        for key in ("vel", "pairs"):
            if key in out:
                out[key] = D.rotate_z(out[key].reshape(len(angles), -1, 3), -angles[:, None]).reshape(len(angles), -1)
        return {k: v.mean(axis=0) for k, v in out.items()}

    def step(self, state: dict, solver: ConsistencySolver | None = None,
             observed_objects: np.ndarray | None = None) -> dict:
        """One policy step with the consistency solve; returns the next state. ``observed_objects``
        (K,3), where given, replace the predicted object points (live-driven neural simulation).
        With ``canonical_frame`` the step runs in the scene turned to the reference object's yaw 0
        and its positions and velocities are turned back; the memory stays in that frame."""
        if not self.cfg.canonical_frame:
            return self._step(state, solver, observed_objects)
        yaw = float(self.yaw(state["pos"]))
        turned = dict(state, pos=D.rotate_z(state["pos"], -yaw), vel=D.rotate_z(state["vel"], -yaw))
        nxt = self._step(turned, solver, None if observed_objects is None else D.rotate_z(observed_objects, -yaw))
        nxt["pos"], nxt["vel"] = D.rotate_z(nxt["pos"], yaw), D.rotate_z(nxt["vel"], yaw)
        return nxt

    def _step(self, state: dict, solver: ConsistencySolver | None, observed_objects: np.ndarray | None) -> dict:
        cfg = self.cfg
        solver = solver or self.solver()
        dt = solver.dt  # the sample period, or a longer step (horizons at the optimizer's knots)
        fast = self.compiled() if observed_objects is None else None
        if fast is not None:  # one step of the compiled loop: the same step without numpy's call overhead (P4)
            return self._step_compiled(fast, state, solver)
        out = self.network_outputs(state)
        if not np.isfinite(np.concatenate(list(out.values()))).all():
            raise PolicyError("network output contains NaN or inf")
        P = len(state["pos"])
        vmax = cfg.max_speed
        v = np.minimum(np.maximum(out["vel"].reshape(P, 3) / VEL_SCALE, -vmax), vmax)  # np.clip costs more
        J = self.body_pooled(out["J"].reshape(self.K, 2)) if cfg.dynamics else None
        trusted = None
        if cfg.masks and cfg.follow_unobserved:
            trusted = state["mask"] & (out["mask"] > 0.0)
            hand = self.body < 2  # with J the objects follow after their velocities are reconciled (below)
            v = follow_bodies(v, state["pos"], trusted | ~hand if J is not None else trusted, self.body)
        v = np.minimum(np.maximum(solver.velocities(v[:2 * KEYPOINTS_PER_HAND], v[2 * KEYPOINTS_PER_HAND:], J),
                                  -vmax), vmax)
        if trusted is not None and J is not None:  # object points unseen follow their reconciled object
            v = follow_bodies(v, state["pos"], trusted | hand, self.body)
        if cfg.rigid_objects:
            n = 2 * KEYPOINTS_PER_HAND
            v[n:] = rigid_velocities(v[n:], state["pos"][n:], self.body[n:] - 2)
        pairs, pmask = None, None
        if cfg.pair_outputs and "pairs" in out and solver.w_pair > 0:
            lay = self.net.layout
            a = state["pos"][lay.anchors]
            # the net predicts a sample period's change; a longer step takes that many
            change = np.clip(out["pairs"].reshape(-1, 3) / PAIR_SCALE * (dt / self.dt), -2 * cfg.max_speed * dt,
                             2 * cfg.max_speed * dt)  # two points approach at most at twice max speed
            pairs = a[lay.pair_j] - a[lay.pair_i] + change
            if cfg.masks:
                am = state["mask"][lay.anchors]
                pmask = (am[lay.pair_j] & am[lay.pair_i]).astype(float)
        pos = solver.positions(state["pos"], v, pairs, pmask)
        if observed_objects is not None:
            pos[2 * KEYPOINTS_PER_HAND:] = observed_objects
        nxt = dict(state)
        nxt["t"] = state.get("t", 0.0) + dt
        nxt["vel"] = (pos - state["pos"]) / dt
        nxt["pos"] = pos
        if cfg.masks:
            nxt["mask"] = out["mask"] > 0.0
        if cfg.tactile:
            nxt["tactile"] = np.minimum(np.maximum(out["tactile"].reshape(2, -1) / TACTILE_SCALE, 0.0), MAX_TACTILE_KPA)
        if cfg.memory:
            Hp = out["H"]
            dH = out["dH"] * self.net.dH_std.numpy() / self.net.H_std.numpy()
            # bounded to +-5 training standard deviations: a linear reservoir driven by demonstration
            # speeds never leaves that range, and an untrained net must not run away through it
            nxt["H"] = np.minimum(np.maximum(solver.memory(Hp, state["H"], dH, dt, cfg.w_memory_prior), -5.0), 5.0)
        if cfg.recurrent:
            nxt["rec"] = out["rec"]
        if not np.isfinite(pos).all():
            raise PolicyError("consistency solve produced NaN positions")
        return nxt

    def _step_compiled(self, fast: C.CompiledRollout, state: dict, solver: ConsistencySolver) -> dict:
        """``_step`` through the compiled loop (configs ``compiled.supports``): the same next state."""
        pos, tact, mem, mask = self._roll_compiled(fast, state, 1, solver)
        nxt = dict(state)
        nxt["t"] = state.get("t", 0.0) + solver.dt
        nxt["vel"] = (pos[0] - state["pos"]) / solver.dt
        nxt["pos"] = pos[0]
        if self.cfg.masks:
            nxt["mask"] = mask
        if self.cfg.tactile:
            nxt["tactile"] = tact[0]
        if self.cfg.memory:
            nxt["H"] = mem[0]
        return nxt

    def rollout(self, start: Demo, steps: int) -> tuple[np.ndarray, np.ndarray]:
        if self.net is None:
            raise PolicyError("fit() or load() first")
        self.net.eval()
        state = self.initial_state(start)
        out = np.empty((steps, len(state["pos"]), 3))
        out[0] = state["pos"]
        out[1:] = self.roll(state, steps - 1)[0]
        n = 2 * KEYPOINTS_PER_HAND
        return out[:, :n].reshape(steps, 2, KEYPOINTS_PER_HAND, 3), out[:, n:]

    # --- checkpoints (state_dict + JSON config; torch.load(weights_only=True)) -----------------
    def state(self) -> dict:
        meta = {"K": self.K, "dt": self.dt, "object_names": self.object_names, "config": self.cfg.to_json(),
                "frame_idx": self.frame_idx.tolist(), "frame_ref": self.frame_ref.tolist()}
        tensors = dict(self.net.state_dict())
        if self.reservoir is not None:
            tensors["reservoir.W_R"] = torch.from_numpy(self.reservoir.W_R)
            tensors["reservoir.W_I"] = torch.from_numpy(self.reservoir.W_I)
        return {"meta": meta, "state_dict": tensors}

    def save(self, path: str) -> None:
        torch.save(self.state(), path)

    @classmethod
    def from_state(cls, ckpt: dict) -> Ours:
        meta = ckpt["meta"]
        self = cls(PolicyConfig.from_json(meta["config"]))
        self.K, self.dt, self.object_names = int(meta["K"]), float(meta["dt"]), list(meta["object_names"])
        if self.cfg.canonical_frame:
            self.frame_idx = np.array(meta["frame_idx"], int)
            self.frame_ref = np.array(meta["frame_ref"], np.float64).reshape(-1, 2)
        self.net = PolicyNet(self.cfg, self.K)
        self.body = self.bodies()
        sd = dict(ckpt["state_dict"])
        if self.cfg.memory:
            self.reservoir = Reservoir.from_arrays(sd.pop("reservoir.W_R").numpy(), sd.pop("reservoir.W_I").numpy())
        self.net.load_state_dict(sd)
        self.net.eval()
        return self

    @classmethod
    def load(cls, path: str) -> Ours:
        return cls.from_state(torch.load(path, weights_only=True))

