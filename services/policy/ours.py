"""The learning method of thesis chapter 7 on one code path; variants are config switches.

Network (7.2.1): dense 2048-512-512-512 ReLU, outputs keypoint velocities (hands and objects),
tactile (7.2.10) and the reservoir's denoised value and rate (7.2.8). Training (7.2.2):
exponentially scaled denoising noise on input positions, subtracted (scaled by f_n) from the
target velocities; rotation about gravity (7.2.4); mirroring with 60/40 hand sampling (7.6.8);
masked losses (7.2.5). Inference: the consistency constraints (7.3-7.5, 7.9-7.10) are solved as
least squares each step (closed form: they are linear and decoupled).

Variants: tactile on/off, memory (reservoir) on/off, time window (16 past samples averaged over
8, 4, 2, 1, 1) instead of memory: the rows of Table 7.1 (1), (2), (3), (4).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass

import numpy as np
import torch
from torch import nn

from services.policy import features as F
from shared.demo import Demo

WINDOW_SPLITS = (8, 4, 2, 1, 1)  # older -> newer, 16 samples
MAX_SPEED = 1.0  # m/s: no keypoint of a hand or object moves faster in these tasks
WORKSPACE_LO = np.array([-0.5, -0.5, 0.0])
WORKSPACE_HI = np.array([0.5, 0.5, 0.6])


@dataclass
class PolicyConfig:
    name: str = "multimodal"
    tactile: bool = True
    memory: bool = True  # recurrent denoising with reservoir activations
    time_window: bool = False
    denoise: bool = True
    noise_base: float = 10.0  # b_n
    noise_exponent: tuple[float, float] = (-3.3, -1.3)  # R_U range: 0.5 mm .. 5 cm
    noise_gain: float = 4.0  # f_n (1/s): how fast a displacement is corrected
    reservoir: int = 32
    hidden: tuple[int, ...] = (2048, 512, 512, 512)
    steps: int = 2500
    batch: int = 256
    lr: float = 1e-3
    left_probability: float = 0.6  # grasping with the left (gripper) hand, 7.6.8
    seed: int = 0


PRESETS = {
    "multimodal": PolicyConfig(),
    "no_tactile": PolicyConfig(name="no_tactile", tactile=False),
    "single_state": PolicyConfig(name="single_state", tactile=False, memory=False),
    "time_window": PolicyConfig(name="time_window", tactile=False, memory=False, time_window=True),
}


class Net(nn.Module):
    def __init__(self, n_in: int, n_out: int, hidden: tuple[int, ...]) -> None:
        super().__init__()
        layers, width = [], n_in
        for h in hidden:
            layers += [nn.Linear(width, h), nn.ReLU()]
            width = h
        layers.append(nn.Linear(width, n_out))
        self.body = nn.Sequential(*layers)
        self.register_buffer("mean", torch.zeros(n_in))
        self.register_buffer("std", torch.ones(n_in))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.body((x - self.mean) / self.std)


class PolicyError(RuntimeError):
    """The policy produced something that must not be used (NaN), or was asked the impossible."""


class Ours:
    """Method of Table 7.1 row (1) and its ablations, behind the common fit/rollout interface."""

    def __init__(self, config: PolicyConfig | str = "multimodal") -> None:
        self.cfg = PRESETS[config] if isinstance(config, str) else config
        self.name = self.cfg.name
        self.net: Net | None = None
        self.train_seconds = 0.0
        self.losses: list[float] = []

    # --- data ---------------------------------------------------------------------------
    def _prepare(self, demos: list[Demo]) -> dict:
        """Every demonstration and its mirror image, flattened into sample arrays (step t -> t+1)."""
        cols: dict[str, list] = {k: [] for k in ("hands", "objects", "hv", "ov", "nh", "no", "hmask", "omask",
                                                 "tactile", "ntactile", "tmask", "H", "nH", "left", "start")}
        offset = 0
        for demo in demos + [F.mirror(d) for d in demos]:
            T = demo.steps
            hv, ov = F.velocities(demo.hands, demo.dt), F.velocities(demo.objects, demo.dt)
            cols["hands"].append(demo.hands[:-1])
            cols["objects"].append(demo.objects[:-1])
            cols["hv"].append(hv[:-1])
            cols["ov"].append(ov[:-1])
            cols["nh"].append(demo.hands[1:])
            cols["no"].append(demo.objects[1:])
            cols["hmask"].append(demo.hand_mask[:-1])
            cols["omask"].append(demo.object_mask[:-1])
            cols["tactile"].append(demo.tactile[:-1])
            cols["ntactile"].append(demo.tactile[1:])
            cols["tmask"].append(demo.tactile_mask[:-1])
            if self.cfg.memory:
                v = np.concatenate([hv.reshape(T, -1), ov.reshape(T, -1)], axis=1)
                m = np.concatenate([np.repeat(demo.hand_mask.reshape(T, -1), 3, axis=1),
                                    np.repeat(demo.object_mask, 3, axis=1)], axis=1)
                H = self.reservoir.run(v * F.VEL_SCALE, m)
                cols["H"].append(H[:-1])
                cols["nH"].append(H[1:])
            cols["left"].append(np.full(T - 1, demo.meta.get("grasp_hand", "left") == "left"))
            cols["start"].append(np.full(T - 1, offset))
            offset += T - 1
        data = {k: np.concatenate(v) for k, v in cols.items() if v}
        left = data["left"]
        p = np.where(left, self.cfg.left_probability / max(left.sum(), 1),
                     (1 - self.cfg.left_probability) / max((~left).sum(), 1))
        data["p"] = p / p.sum()
        return data

    def _window(self, x: np.ndarray, t: np.ndarray, start: np.ndarray | None = None) -> np.ndarray:
        """Averages of the 16 samples before t over 8,4,2,1,1, clamped at the episode start."""
        start = np.zeros_like(t) if start is None else start
        parts, back = [], 16
        for n in WINDOW_SPLITS:
            idx = np.maximum(t[:, None] - back + np.arange(n)[None], start[:, None])
            parts.append(x[idx].mean(axis=1))
            back -= n
        return np.concatenate(parts, axis=-1)

    def _batch(self, data: dict, rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        cfg = self.cfg
        idx = rng.choice(len(data["p"]), n, p=data["p"])
        hands, objects = data["hands"][idx], data["objects"][idx]
        hv, ov = data["hv"][idx], data["ov"][idx]
        dt = self.dt
        thv, tov = (data["nh"][idx] - hands) / dt, (data["no"][idx] - objects) / dt
        scale = np.zeros(n)
        if cfg.denoise:  # 7.6-7.7: one random exponent per sample, noise subtracted from the targets
            scale = cfg.noise_base ** rng.uniform(*cfg.noise_exponent, n)
            nh = rng.normal(0, 1, hands.shape) * scale[:, None, None, None]
            no = rng.normal(0, 1, objects.shape) * scale[:, None, None] * 0.3  # objects are observed: smaller
            hands, objects = hands + nh, objects + no
            thv, tov = thv - nh * cfg.noise_gain, tov - no * cfg.noise_gain
        angle = rng.uniform(0, 2 * np.pi, n)  # 7.2.4: rotation about gravity, one angle per sample

        def rot(x: np.ndarray) -> np.ndarray:
            return F.rotate_z(x, angle.reshape(n, *[1] * (x.ndim - 2)))

        hands, objects, hv, ov, thv, tov = map(rot, (hands, objects, hv, ov, thv, tov))
        x = [F.state_features(hands, objects, hv, ov)]
        if cfg.time_window:
            flat_h = data["hands"].reshape(len(data["hands"]), -1)
            flat_o = data["objects"].reshape(len(data["objects"]), -1)
            wh = self._window(flat_h, idx, data["start"][idx]).reshape(n, 5, 2, 21, 3)
            wo = self._window(flat_o, idx, data["start"][idx]).reshape(n, 5, -1, 3)
            x.append(self._window_features(rot_window(wh, angle), rot_window(wo, angle), hands, objects))
        if cfg.tactile:
            x += [data["tactile"][idx].reshape(n, -1) * F.TACTILE_SCALE, data["tmask"][idx].reshape(n, -1)]
        if cfg.memory:
            x.append(data["H"][idx] + rng.normal(0, 1, (n, cfg.reservoir)) * scale[:, None] * 10)
        y = [thv.reshape(n, -1) * F.VEL_SCALE, tov.reshape(n, -1) * F.VEL_SCALE]
        w = [np.repeat(data["hmask"][idx].reshape(n, -1), 3, axis=1), np.repeat(data["omask"][idx], 3, axis=1)]
        if cfg.tactile:
            y.append(data["ntactile"][idx].reshape(n, -1) * F.TACTILE_SCALE)
            w.append(data["tmask"][idx].reshape(n, -1))
        if cfg.memory:
            y += [data["H"][idx], (data["nH"][idx] - data["H"][idx]) / dt * 0.1]
            w += [np.ones((n, cfg.reservoir)), np.ones((n, cfg.reservoir))]
        return (np.concatenate(x, axis=1).astype(np.float32), np.concatenate(y, axis=1).astype(np.float32),
                np.concatenate(w, axis=1).astype(np.float32))

    def _window_features(self, wh: np.ndarray, wo: np.ndarray, hands: np.ndarray, objects: np.ndarray) -> np.ndarray:
        """Past window averages (B,5,...) relative to the current positions (translation invariant)."""
        b = hands.shape[0]
        return np.concatenate([((wh - hands[:, None]) * F.POS_SCALE).reshape(b, -1),
                               ((wo - objects[:, None]) * F.POS_SCALE).reshape(b, -1)], axis=1)

    # --- training -----------------------------------------------------------------------
    def fit(self, train: list[Demo], progress: bool = True) -> None:
        from tqdm import tqdm

        cfg = self.cfg
        torch.manual_seed(cfg.seed)
        rng = np.random.default_rng(cfg.seed)
        self.K = train[0].objects.shape[1]
        self.dt = train[0].dt
        if cfg.memory:
            n_v = (42 + self.K) * 3
            self.reservoir = F.Reservoir(n_v, cfg.reservoir, seed=cfg.seed)
        data = self._prepare(train)
        if cfg.memory:
            self.H0 = data["H"][np.unique(data["start"])].mean(axis=0)
            self.H_lo, self.H_hi = data["H"].min(axis=0), data["H"].max(axis=0)
        x0, y0, _ = self._batch(data, rng, 2048)
        self.net = Net(x0.shape[1], y0.shape[1], cfg.hidden)
        self.net.mean.copy_(torch.from_numpy(x0.mean(0)))
        self.net.std.copy_(torch.from_numpy(x0.std(0) + 1e-3))
        opt = torch.optim.Adam(self.net.parameters(), lr=cfg.lr)
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, cfg.steps)
        t0 = time.perf_counter()
        bar = tqdm(range(cfg.steps), desc=f"train {self.name}", disable=not progress, leave=False)
        for _ in bar:
            x, y, w = (torch.from_numpy(a) for a in self._batch(data, rng, cfg.batch))
            loss = ((self.net(x) - y) ** 2 * w).sum() / w.sum()
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            self.losses.append(loss.item())
            if len(self.losses) % 50 == 0:
                bar.set_postfix(loss=f"{np.mean(self.losses[-50:]):.4f}")
        self.train_seconds = time.perf_counter() - t0
        self.net.eval()

    # --- inference ----------------------------------------------------------------------
    def step(self, state: dict) -> dict:
        """One policy step with the consistency solve: returns the next state."""
        cfg = self.cfg
        hands, objects = state["hands"], state["objects"]
        x = [F.state_features(hands[None], objects[None], state["hv"][None], state["ov"][None])[0]]
        if cfg.time_window:
            hist_h = np.array(state["history_h"][-16:])
            hist_o = np.array(state["history_o"][-16:])
            t = np.array([len(hist_h) - 1])
            wh = self._window(hist_h.reshape(len(hist_h), -1), t).reshape(1, 5, 2, 21, 3)
            wo = self._window(hist_o.reshape(len(hist_o), -1), t).reshape(1, 5, -1, 3)
            x.append(self._window_features(wh, wo, hands[None], objects[None])[0])
        if cfg.tactile:
            x += [state["tactile"].ravel() * F.TACTILE_SCALE, state["tactile_mask"].ravel()]
        if cfg.memory:
            x.append(state["H"])
        with torch.no_grad():
            out = self.net(torch.from_numpy(np.concatenate(x).astype(np.float32)[None]))[0].numpy()
        if not np.isfinite(out).all():
            raise PolicyError("network output contains NaN")
        nh, no = hands.size, objects.size
        hv = out[:nh].reshape(hands.shape) / F.VEL_SCALE
        ov = out[nh:nh + no].reshape(objects.shape) / F.VEL_SCALE
        k = nh + no
        nxt = dict(state)
        # 7.5: positions consistent with velocities; with the speed and workspace bounds the
        # least-squares solution is the clipped integral.
        hv, ov = np.clip(hv, -MAX_SPEED, MAX_SPEED), np.clip(ov, -MAX_SPEED, MAX_SPEED)
        nxt["hands"] = np.clip(hands + hv * self.dt, WORKSPACE_LO, WORKSPACE_HI)
        nxt["objects"] = np.clip(objects + ov * self.dt, WORKSPACE_LO, WORKSPACE_HI)
        nxt["hv"], nxt["ov"] = hv, ov
        if cfg.tactile:
            nxt["tactile"] = np.clip(out[k:k + 12].reshape(2, 6) / F.TACTILE_SCALE, 0, None)
            k += 12
        if cfg.memory:
            h_pred, dh = out[k:k + cfg.reservoir], out[k + cfg.reservoir:k + 2 * cfg.reservoir] / 0.1
            # 7.9 + 7.10 in least squares: H_t = argmin |H - H_P|^2 + |H - H_{t-1} - dH dt|^2
            # bounded to the range seen in training (the activations of a linear reservoir driven by
            # demonstration speeds never leave it)
            nxt["H"] = np.clip(0.5 * (h_pred + state["H"] + dh * self.dt), self.H_lo, self.H_hi)
        if cfg.time_window:
            nxt["history_h"] = state["history_h"] + [nxt["hands"]]
            nxt["history_o"] = state["history_o"] + [nxt["objects"]]
        return nxt

    def initial_state(self, start: Demo) -> dict:
        state = {"hands": start.hands[0].astype(float), "objects": start.objects[0].astype(float),
                 "hv": np.zeros((2, 21, 3)), "ov": np.zeros_like(start.objects[0], float),
                 "tactile": start.tactile[0].astype(float), "tactile_mask": start.tactile_mask[0].astype(float)}
        if self.cfg.memory:
            state["H"] = self.H0.copy()
        if self.cfg.time_window:
            state["history_h"] = [state["hands"]]
            state["history_o"] = [state["objects"]]
        return state

    def rollout(self, start: Demo, steps: int) -> tuple[np.ndarray, np.ndarray]:
        if self.net is None:
            raise PolicyError("fit() or load() first")
        state = self.initial_state(start)
        hands, objects = [state["hands"]], [state["objects"]]
        for _ in range(steps - 1):
            state = self.step(state)
            hands.append(state["hands"])
            objects.append(state["objects"])
        return np.array(hands), np.array(objects)

    # --- checkpoints --------------------------------------------------------------------
    def save(self, path: str) -> None:
        extra = {"K": self.K, "dt": self.dt}
        tensors = {"net": self.net.state_dict()}
        if self.cfg.memory:
            tensors["reservoir"] = {"W_R": torch.from_numpy(self.reservoir.W_R),
                                    "W_I": torch.from_numpy(self.reservoir.W_I), "H0": torch.from_numpy(self.H0),
                                    "H_lo": torch.from_numpy(self.H_lo), "H_hi": torch.from_numpy(self.H_hi)}
        torch.save({"config": asdict(self.cfg), "extra": extra, "tensors": tensors}, path)

    @classmethod
    def load(cls, path: str) -> Ours:
        ckpt = torch.load(path, weights_only=True)
        cfg = dict(ckpt["config"])
        cfg["hidden"], cfg["noise_exponent"] = tuple(cfg["hidden"]), tuple(cfg["noise_exponent"])
        self = cls(PolicyConfig(**cfg))
        self.K, self.dt = ckpt["extra"]["K"], ckpt["extra"]["dt"]
        state = ckpt["tensors"]["net"]
        self.net = Net(state["mean"].shape[0], state["body." + str(2 * len(self.cfg.hidden)) + ".weight"].shape[0],
                       self.cfg.hidden)
        self.net.load_state_dict(state)
        self.net.eval()
        if self.cfg.memory:
            r = ckpt["tensors"]["reservoir"]
            self.reservoir = F.Reservoir(r["W_I"].shape[1], self.cfg.reservoir)
            self.reservoir.W_R, self.reservoir.W_I = r["W_R"].numpy(), r["W_I"].numpy()
            self.H0, self.H_lo, self.H_hi = r["H0"].numpy(), r["H_lo"].numpy(), r["H_hi"].numpy()
        return self


def rot_window(w: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rotate window averages (B,5,...,3) by per-sample angles."""
    return F.rotate_z(w, angle.reshape(len(angle), *[1] * (w.ndim - 2)))
