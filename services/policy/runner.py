"""The policy as the node runs it, and the neural simulation (recursive rollout, thesis 7.6.1/7.6.8).

``PolicyRunner``: holds the latest observed scene, advances the memory each observation, gives the
next positions (``step``) or a horizon rollout for the trajectory optimizer (``horizon``); never
returns NaN: it raises ``PolicyInputError`` for unusable observations and ``PolicyError`` when the
network itself produces NaN. The predicted tactile of the last step is exposed as ``efforts``
(7.2.10: added to the robot's control efforts).
``simulate``: positions fed back as inputs step after step; with ``observed_objects`` the object
points come from observation instead of the model (the interactive mode of 7.6.1).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from services.policy.model import Policy, PolicyError
from shared.demo import KEYPOINTS_PER_HAND, TACTILE_REGIONS, Demo

HAND_POINTS = 2 * KEYPOINTS_PER_HAND


class PolicyInputError(ValueError):
    """An observation the policy cannot use (NaN in observed points, wrong shapes)."""


@dataclass
class Rollout:
    hands: np.ndarray  # (T,2,21,3)
    objects: np.ndarray  # (T,K,3)
    tactile: np.ndarray  # (T,2,R) predicted (zeros without the tactile modality)
    memory: np.ndarray  # (T,size) reservoir activations (empty without memory)


@dataclass
class SceneObs:
    """One observed scene (what recon publishes), in arrays."""

    hands: np.ndarray  # (2,21,3)
    hand_mask: np.ndarray  # (2,21)
    objects: np.ndarray  # (K,3)
    object_mask: np.ndarray  # (K,)
    tactile: np.ndarray | None = None  # (2,R) kPa
    tactile_mask: np.ndarray | None = None  # (2,R)

    @classmethod
    def from_msg(cls, msg) -> SceneObs:
        n_obj = len(msg.object_names)
        tact = np.asarray(msg.tactile, float)
        tmask = np.asarray(msg.tactile_mask, bool)
        return cls(np.asarray(msg.hand_keypoints, float).reshape(2, KEYPOINTS_PER_HAND, 3),
                   np.asarray(msg.hand_mask, bool).reshape(2, KEYPOINTS_PER_HAND),
                   np.asarray(msg.object_keypoints, float).reshape(n_obj, 3), np.asarray(msg.object_mask, bool),
                   tact.reshape(2, -1) if tact.size else None, tmask.reshape(2, -1) if tmask.size else None)


def simulate(model: Policy, start_state: Demo | dict, steps: int,
             observed_objects: np.ndarray | None = None) -> Rollout:
    """Recursive neural simulation for ``steps`` samples (the first is the start state)."""
    state = model.initial_state(start_state) if isinstance(start_state, Demo) else dict(start_state)
    if "window_pos" not in state:  # a state given without its history starts an episode
        state = model.start_window(state)
    if observed_objects is not None:
        observed_objects = np.asarray(observed_objects, float)
        if observed_objects.shape[1:] != (model.K, 3) or len(observed_objects) < steps:
            raise PolicyInputError(f"observed_objects must be ({steps},{model.K},3), got {observed_objects.shape}")
        if not np.isfinite(observed_objects[:steps]).all():
            raise PolicyInputError("observed_objects contains NaN")
    P = len(state["pos"])
    pos = np.empty((steps, P, 3))
    tact = np.zeros((steps, 2, len(TACTILE_REGIONS)))
    mem = np.zeros((steps, len(state.get("H", []))))
    pos[0], tact[0] = state["pos"], state["tactile"]
    if "H" in state:
        mem[0] = state["H"]
    pos[1:], tact[1:], mem[1:] = model.roll(state, steps - 1, None,
                                            None if observed_objects is None else observed_objects[1:steps])
    return Rollout(pos[:, :HAND_POINTS].reshape(steps, 2, KEYPOINTS_PER_HAND, 3), pos[:, HAND_POINTS:], tact, mem)


class PolicyRunner:
    """The policy as the service runs it: observations in, next positions and horizons out.

    The running state is the neural simulation's (7.6.1) with observations merged in: each step's
    predicted state (positions, masks, touch, memory, time window) is what the next step starts
    from, and an observation replaces what it observed. Touch the scene does not read (no glove, or
    a robot) stays the net's own prediction, fed back on the hands ``glove`` marks, as the neural
    simulation feeds it back on the gloved hands of its start state; training gives the net touch
    only on gloved hands (``tmask``), so without a glove reading the net gets none unless ``glove``
    says where its prediction stands in for one."""

    def __init__(self, model: Policy, glove: np.ndarray | None = None) -> None:
        self.model = model
        self.glove = np.zeros(2, bool) if glove is None else np.asarray(glove, bool).reshape(2)
        self.state: dict | None = None  # the state the last step started from (horizons roll from it)
        self.predicted: dict | None = None  # the last step's next state (the next step starts from it)
        self.efforts = np.zeros((2, len(TACTILE_REGIONS)))  # predicted tactile, kPa (7.2.10)
        self.horizon_tactile = np.zeros((0, 2, len(TACTILE_REGIONS)))  # of the last horizon()
        self.scene: SceneObs | None = None

    @classmethod
    def from_checkpoint(cls, path: str | Path) -> PolicyRunner:
        return cls(Policy.load(str(path)))

    def reset(self) -> None:
        self.state = self.predicted = None

    def observe(self, scene: SceneObs) -> dict:
        """Merges an observation into the running state: observed points replace the predicted ones
        (occluded or NaN points keep their prediction), the masks are the observation's, touch a
        glove read replaces the predicted touch."""
        m = self.model
        if scene.objects.shape != (m.K, 3) or scene.hands.shape != (2, KEYPOINTS_PER_HAND, 3):
            raise PolicyInputError(f"scene has hands {scene.hands.shape} and objects {scene.objects.shape}; "
                                   f"the policy was trained with (2,21,3) and ({m.K},3)")
        pos = np.concatenate([scene.hands.reshape(-1, 3), scene.objects]).astype(float)
        mask = np.concatenate([np.asarray(scene.hand_mask, bool).ravel(), np.asarray(scene.object_mask, bool)])
        finite = np.isfinite(pos).all(-1)
        mask &= finite
        seen = mask if m.cfg.masks else np.ones_like(mask)
        if self.state is None:
            if not finite.all():
                raise PolicyInputError(f"first scene has NaN keypoints at {np.flatnonzero(~finite).tolist()}; "
                                       f"cannot start from it")
            regions = len(TACTILE_REGIONS)
            start = {"pos": pos, "vel": np.zeros_like(pos), "mask": seen, "tactile": np.zeros((2, regions)),
                     "tmask": np.repeat(self.glove[:, None], regions, axis=1)}
            if m.cfg.memory:
                start["H"] = m.initial_memory()
            self.state = m.start_window(start)
        else:
            base = self.predicted if self.predicted is not None else self.state
            merged = np.where(mask[:, None], pos, base["pos"])
            self.state = dict(base, pos=merged, vel=(merged - self.state["pos"]) / m.dt, mask=seen)
        self.predicted = None
        if scene.tactile is not None and scene.tactile_mask is not None:
            t, tm = np.asarray(scene.tactile, float), np.asarray(scene.tactile_mask, bool)
            tm &= np.isfinite(t)
            self.state["tactile"] = np.where(tm, np.nan_to_num(t), self.state["tactile"])
            self.state["tmask"] = tm
        self.scene = scene
        return self.state

    def step(self, scene_obs: SceneObs | None) -> np.ndarray:
        """Observe (None: no new observation, run on the last prediction), then one policy step:
        next positions (P,3) of hands then objects. The memory advances with the step, so call it
        once per network sample period."""
        if scene_obs is None and self.state is None:
            raise PolicyInputError("no scene observed yet")
        if scene_obs is not None:
            self.observe(scene_obs)
        elif self.predicted is not None:
            self.state, self.predicted = self.predicted, None
        nxt = self.model.step(self.state)
        self._check(nxt["pos"])
        self.predicted = nxt
        self.efforts = nxt["tactile"]
        return nxt["pos"]

    def horizon(self, scene_obs: SceneObs | None, steps: int, dt: float | None = None) -> np.ndarray:
        """Rollout of ``steps`` samples from the latest observation (steps, P, 3), ``dt`` apart
        (default the sample period; the trajectory optimizer's knot spacing costs fewer network
        passes for the same look-ahead); after a step its first sample is that step's prediction.
        The running state is not advanced by the look-ahead."""
        if scene_obs is not None:
            self.observe(scene_obs)
        if self.state is None:
            raise PolicyInputError("no scene observed yet")
        out, tactile, _ = self.model.roll(self.state, steps, dt)
        self._check(out)
        self.horizon_tactile = tactile
        return out

    @staticmethod
    def _check(x: np.ndarray) -> None:
        if not np.isfinite(x).all():
            raise PolicyError("policy output contains NaN")
