"""A trained chapter-7 policy: the network, what it was trained on, and its rollout.

``Policy`` holds a ``PolicyNet`` (network.py) with its configs (config.py), the object point
names and sample period of its training data; ``roll`` / ``step`` / ``rollout`` run the recursive
neural simulation (7.6.1) through the compiled loop (compiled.py), rebuilt whenever the weights
change. Checkpoints (``save`` / ``load``) are a state_dict and JSON metadata, readable with
``torch.load(weights_only=True)``; ``xm train`` (learning/) writes them.
"""

from __future__ import annotations

import json
import os

import numpy as np
import torch

from services.policy import compiled as C
from services.policy.config import InferenceConfig, ModelConfig, from_json, to_json
from services.policy.folded import FoldedNet
from services.policy.network import PolicyNet
from services.policy.window import pad_history, push_history
from shared.demo import KEYPOINTS_PER_HAND, Demo

MAX_TACTILE_KPA = 500.0  # above any glove reading: bounds the tactile feedback of an untrained net
CHECKPOINT_FORMAT = 2  # meta["format"]; checkpoints without it came from the single-config layout


class PolicyError(RuntimeError):
    """The policy produced something that must not be used (NaN), or was used out of order."""


def object_groups(object_names: list[str]) -> np.ndarray:
    """Body index per object keypoint from names "<object>/<point>" (first seen, first numbered)."""
    bodies: dict[str, int] = {}
    return np.array([bodies.setdefault(n.split("/")[0], len(bodies)) for n in object_names], int)


class Policy:
    """A network and what it needs to roll out: its configs, K object points and their names, dt."""

    def __init__(self, net: PolicyNet, inference: InferenceConfig, dt: float, object_names: list[str],
                 name: str = "policy", record: dict | None = None) -> None:
        self.net, self.cfg, self.inference = net, net.cfg, inference
        self.K, self.dt, self.object_names, self.name = net.layout.K, float(dt), list(object_names), name
        self.record = dict(record or {})  # training's own settings, kept in the checkpoint for the record
        self.extra_tensors: dict[str, torch.Tensor] = {}  # saved beside the weights (training's reservoir)
        self.body = np.concatenate([np.repeat([0, 1], KEYPOINTS_PER_HAND), 2 + object_groups(self.object_names)])
        self._folded: FoldedNet | None = None
        self._folded_tensors = [*net.parameters(), *net.buffers()]
        self._folded_stamp: tuple = ()
        self._compiled: C.CompiledRollout | None = None

    def pool_matrix(self) -> np.ndarray:
        """(K,K): each object point's J_D replaced by its body's mean (``body_dynamics``), so that a
        point hidden in the hand (never seen moving, so never trained) moves like its seen ones."""
        groups = object_groups(self.object_names)
        A = (groups[:, None] == groups[None]).astype(np.float64)
        return A / A.sum(1, keepdims=True)

    # --- the compiled loop ---------------------------------------------------------------------
    def weights_updated(self) -> None:
        """The weights changed in a way their version counters do not show (a fused optimizer step):
        the folded copy is rebuilt on next use."""
        self._folded = None

    def compiled(self) -> C.CompiledRollout:
        """The compiled rollout over the current weights (folded again whenever they changed)."""
        stamp = tuple(t._version for t in self._folded_tensors)  # any in-place update (optimizer, loading) bumps it
        if self._folded is None or self._folded_stamp != stamp:
            keys = tuple(k for k in self.net.slices if k != "pairs")  # the pair outputs train, nothing reads them
            self._folded, self._folded_stamp = FoldedNet(self.net, keys), stamp
        if self._compiled is None or self._compiled.fold is not self._folded:
            self._compiled = C.CompiledRollout(self, self._folded, MAX_TACTILE_KPA)
        return self._compiled

    def initial_state(self, start: Demo) -> dict:
        """The state at a demonstration's first sample: positions, zero velocities, masks, touch, memory."""
        if not np.isfinite(start.hands[0]).all() or not np.isfinite(start.objects[0]).all():
            raise PolicyError(f"start state of {start.meta.get('demo', '?')} has NaN keypoints")
        if start.objects.shape[1] != self.K:
            raise PolicyError(f"start state has {start.objects.shape[1]} object points; trained with {self.K}")
        pos = np.concatenate([start.hands[0].reshape(-1, 3), start.objects[0]]).astype(np.float64)
        mask = np.concatenate([start.hand_mask[0].reshape(-1), start.object_mask[0]]).astype(bool)
        state = {"pos": pos, "vel": np.zeros_like(pos), "mask": mask if self.cfg.masks else np.ones_like(mask),
                 "tactile": start.tactile[0].astype(np.float64), "tmask": start.tactile_mask[0].astype(bool)}
        if self.cfg.memory:
            state["H"] = self.initial_memory()
        return self.start_window(state)

    def start_window(self, state: dict) -> dict:
        """``state`` with the time window's history at an episode start (its samples padded with this
        one), where the net has a window; the state itself otherwise."""
        if not self.cfg.window:
            return state
        return dict(state, window_pos=pad_history(state["pos"], self.cfg.window),
                    window_mask=pad_history(state["mask"], self.cfg.window))

    def initial_memory(self) -> np.ndarray:
        """The normalized reservoir state at an episode start (the training starts' mean)."""
        return ((self.net.H0 - self.net.H_mean) / self.net.H_std).numpy().astype(np.float64)

    def roll(self, state: dict, steps: int, dt: float | None = None, observed_objects: np.ndarray | None = None
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``steps`` policy steps of ``dt`` (default the sample period; a horizon may be rolled out at
        the trajectory optimizer's knot spacing instead, 7.16) from ``state``, which is not changed:
        positions (S,P,3), tactile (S,2,R) and memory (S,size) after each. ``observed_objects``
        (S,K,3), where given, replace the predicted object points step by step."""
        if observed_objects is None:
            return self._roll(state, steps, dt)[:3]
        pos = np.empty((steps, *np.shape(state["pos"])))
        tact = np.empty((steps, *np.shape(state["tactile"])))
        mem = np.empty((steps, len(state.get("H", []))))
        for t in range(steps):
            state = self.step(state, dt, observed_objects[t])
            pos[t], tact[t] = state["pos"], state["tactile"]
            if "H" in state:
                mem[t] = state["H"]
        return pos, tact, mem

    def _roll(self, state: dict, steps: int, dt: float | None
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        w_dyn = self.inference.w_dyn if self.cfg.dynamics else 0.0
        pos, tact, mem, mask, status = self.compiled()(state, steps, dt or self.dt, w_dyn)
        if status == C.NET_NAN:
            raise PolicyError("network output contains NaN or inf")
        if status == C.POS_NAN:
            raise PolicyError("consistency solve produced NaN positions")
        return pos, tact, mem, mask

    def step(self, state: dict, dt: float | None = None, observed_objects: np.ndarray | None = None) -> dict:
        """One policy step with the consistency solve; returns the next state (positions, velocities,
        mask, tactile, memory, time window history, time). ``observed_objects`` (K,3), where given,
        replace the predicted object points (live-driven neural simulation)."""
        dt = dt or self.dt
        pos, tact, mem, mask = self._roll(state, 1, dt)
        nxt = dict(state)
        nxt["t"] = state.get("t", 0.0) + dt
        nxt["pos"] = pos[0]
        if observed_objects is not None:
            nxt["pos"][2 * KEYPOINTS_PER_HAND:] = observed_objects
        nxt["vel"] = (nxt["pos"] - state["pos"]) / dt
        if self.cfg.masks:
            nxt["mask"] = mask
        if self.cfg.tactile:
            nxt["tactile"] = tact[0]
        if self.cfg.memory:
            nxt["H"] = mem[0]
        if self.cfg.window:  # the step's own sample joins the history
            nxt["window_pos"] = push_history(state["window_pos"], state["pos"])
            nxt["window_mask"] = push_history(state["window_mask"], state["mask"])
        return nxt

    def rollout(self, start: Demo, steps: int) -> tuple[np.ndarray, np.ndarray]:
        """Neural simulation from a demonstration's start state: hands (steps,2,21,3), objects (steps,K,3)."""
        state = self.initial_state(start)
        out = np.empty((steps, len(state["pos"]), 3))
        out[0] = state["pos"]
        out[1:] = self.roll(state, steps - 1)[0]
        n = 2 * KEYPOINTS_PER_HAND
        return out[:, :n].reshape(steps, 2, KEYPOINTS_PER_HAND, 3), out[:, n:]

    # --- checkpoints (state_dict + JSON metadata; torch.load(weights_only=True)) ---------------
    def state(self) -> dict:
        meta = {"format": CHECKPOINT_FORMAT, "name": self.name, "K": self.K, "dt": self.dt,
                "object_names": self.object_names, "model": to_json(self.cfg), "inference": to_json(self.inference),
                "training": json.dumps(self.record)}
        return {"meta": meta, "state_dict": {**self.net.state_dict(), **self.extra_tensors}}

    def save(self, path: str) -> None:
        """Written whole or not at all (one rename): the policy service loads a checkpoint as soon as it appears."""
        tmp = f"{path}.tmp"
        torch.save(self.state(), tmp)
        os.replace(tmp, path)

    @classmethod
    def from_state(cls, ckpt: dict) -> Policy:
        meta = ckpt["meta"]
        if meta.get("format") != CHECKPOINT_FORMAT:
            raise PolicyError(f"checkpoint format {meta.get('format', 1)}, this code reads {CHECKPOINT_FORMAT}: "
                              f"train it again with `xm train`")
        try:
            net = PolicyNet(from_json(ModelConfig, meta["model"]), int(meta["K"]))
            inference = from_json(InferenceConfig, meta["inference"])
        except (KeyError, TypeError, ValueError) as exc:
            raise PolicyError(f"checkpoint metadata unusable: {exc}") from exc
        sd = dict(ckpt["state_dict"])
        extra = {k: sd.pop(k) for k in list(sd) if k.startswith("reservoir.")}
        net.load_state_dict(sd)
        net.eval()
        self = cls(net, inference, float(meta["dt"]), list(meta["object_names"]), str(meta.get("name", "policy")),
                   json.loads(meta.get("training", "{}")))
        self.extra_tensors = extra
        return self

    @classmethod
    def load(cls, path: str) -> Policy:
        return cls.from_state(torch.load(path, weights_only=True))
