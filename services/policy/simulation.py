"""The neural simulation on request (thesis 7.6.1): a checkpoint rolled out from a scene (no Zenoh).

``Simulator.rollout`` answers the policy node's ``@cmd/simulate``: the network of a checkpoint
(the served one unless another is named; loaded once and kept, apart from the instance that
plans, so a rollout never touches the planning state) starts from a scene (the latest observed,
or one given in the request: a demonstration's frame) and runs on its own predictions for the
requested seconds. It is called in a worker thread, never in the node's event loop; one rollout
runs at a time and a second request meanwhile is refused with the reason.
"""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np

from services.policy.model import Policy
from services.policy.runner import PolicyInputError, PolicyRunner, SceneObs, simulate
from shared.demo import KEYPOINTS_PER_HAND, TACTILE_REGIONS

MAX_SECONDS = 20.0
MAX_STEPS = 1000


class SimulationError(ValueError):
    """A request the simulation cannot answer; the message says why."""


def scene_from_request(start: dict) -> SceneObs:
    """``{"hands": [2*21*3], "hand_mask": [42], "objects": [K*3], "object_mask": [K]}`` -> a scene."""
    try:
        hands = np.asarray(start["hands"], float).reshape(2, KEYPOINTS_PER_HAND, 3)
        objects = np.asarray(start["objects"], float).reshape(-1, 3)
        hand_mask = np.asarray(start.get("hand_mask", np.ones(2 * KEYPOINTS_PER_HAND)), bool).reshape(2, -1)
        object_mask = np.asarray(start.get("object_mask", np.ones(len(objects))), bool).reshape(-1)
    except (KeyError, TypeError, ValueError) as exc:
        raise SimulationError(f"start scene unusable ({exc}): give hands (2*21*3 numbers), objects (K*3), "
                              f"hand_mask (42) and object_mask (K)") from None
    if object_mask.shape != (len(objects),) or hand_mask.shape != (2, KEYPOINTS_PER_HAND):
        raise SimulationError(f"start scene masks {hand_mask.shape} / {object_mask.shape} do not match its points")
    return SceneObs(hands, hand_mask, objects, object_mask)


class Simulator:
    def __init__(self) -> None:
        self._models: dict[Path, tuple[float, Policy]] = {}  # checkpoint -> (its mtime, the loaded network)
        self._busy = threading.Lock()

    def model(self, checkpoint: Path) -> Policy:
        """The checkpoint's network, loaded again when the file changed."""
        try:
            mtime = checkpoint.stat().st_mtime
        except OSError:
            raise SimulationError(f"checkpoint {checkpoint} is not a file") from None
        kept = self._models.get(checkpoint)
        if kept is None or kept[0] != mtime:
            try:
                kept = (mtime, Policy.load(str(checkpoint)))
            except Exception as exc:  # torch raises unrelated types for files that are no checkpoint
                raise SimulationError(f"checkpoint {checkpoint} unusable ({type(exc).__name__}: "
                                      f"{str(exc)[:200]})") from None
            self._models = {checkpoint: kept}  # one kept: a teacher compares few at a time
        return kept[1]

    def rollout(self, checkpoint: Path, scene: SceneObs, seconds: float) -> dict:
        """The reply of ``@cmd/simulate``: predicted hands, objects and tactile per step, flat."""
        if not 0 < seconds <= MAX_SECONDS:
            raise SimulationError(f"seconds must be in (0, {MAX_SECONDS:g}], got {seconds}")
        if not self._busy.acquire(blocking=False):
            raise SimulationError("a neural simulation is running; ask again once it has answered")
        try:
            model = self.model(checkpoint)
            steps = min(MAX_STEPS, max(2, int(round(seconds / model.dt)) + 1))
            runner = PolicyRunner(model)
            try:
                state = runner.observe(scene)
            except PolicyInputError as exc:
                raise SimulationError(str(exc)) from None
            out = simulate(model, state, steps)
        finally:
            self._busy.release()
        if not (np.isfinite(out.hands).all() and np.isfinite(out.objects).all()):
            raise SimulationError("the network's rollout diverged (NaN); nothing to show")
        return {"ok": True, "checkpoint": str(checkpoint), "policy": model.name, "dt": model.dt, "steps": steps,
                "object_names": model.object_names, "tactile_regions": list(TACTILE_REGIONS),
                "tactile_predicted": bool(model.cfg.tactile),
                "hands": _flat(out.hands, 5), "objects": _flat(out.objects, 5), "tactile": _flat(out.tactile, 2)}


def _flat(x: np.ndarray, decimals: int) -> list[float]:
    """Rounded (metres to 10 um, kPa to 10 Pa): the reply is JSON, and its size matters."""
    return np.round(np.asarray(x, float), decimals).ravel().tolist()
