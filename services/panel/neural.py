"""The dashboard's Neural simulation folder: a checkpoint rolled out from a scene, drawn as a ghost.

The rollout runs in the policy service (``@cmd/simulate``, services/policy/simulation.py); this
folder's own thread (never the panel's event loop) sends the request: from the live scene the
policy last observed, or from the reviewed demonstration at the scrubber's position. With
"follow the live scene" it asks again every ``FOLLOW_S``, so as objects move in front of the
cameras the simulated trajectories follow (thesis 7.6.1). The event loop draws the reply: the
predicted paths of the wrists, fingertips and objects as trails, a ghost of the hands and objects
moving along them (looping), and the predicted tactile of both hands at the ghost's time.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import viser

from services.panel import view
from services.panel.jobs import Model
from shared.demo import FINGERTIPS, KEYPOINTS_PER_HAND

log = logging.getLogger("xm")
SIMULATE = "xm/policy/main/@cmd/simulate"
SERVED = "the served network"
LIVE, REVIEWED = "the live scene", "the reviewed demonstration (scrubber)"
FOLLOW_S = 1.0  # re-simulation period while following the live scene
TIMEOUT_S = 30.0  # a first rollout of a checkpoint loads it
TRAIL_POINTS = (0, *FINGERTIPS.values())  # wrist and fingertips: their predicted paths are drawn
GHOST = 0.55  # ghost colours: this much of the way to white
TACTILE_VMAX = 30.0  # kPa at the top of the predicted-tactile colour map


def ghost(color: tuple[int, int, int]) -> tuple[int, int, int]:
    return tuple(int(c + (255 - c) * GHOST) for c in color)


@dataclass(eq=False)  # compared by identity: which reply is drawn
class Rollout:
    """A ``@cmd/simulate`` reply in arrays."""
    dt: float
    hands: np.ndarray  # (T,2,21,3)
    objects: np.ndarray  # (T,K,3)
    tactile: np.ndarray  # (T,2,R) kPa
    tactile_predicted: bool
    policy: str
    source: str
    received: float  # monotonic

    @classmethod
    def from_reply(cls, reply: dict, source: str, now: float) -> Rollout:
        steps = int(reply["steps"])
        return cls(float(reply["dt"]),
                   np.reshape(np.asarray(reply["hands"], np.float32), (steps, 2, KEYPOINTS_PER_HAND, 3)),
                   np.reshape(np.asarray(reply["objects"], np.float32), (steps, -1, 3)),
                   np.reshape(np.asarray(reply["tactile"], np.float32), (steps, 2, -1)),
                   bool(reply.get("tactile_predicted")), str(reply.get("policy", "?")), source, now)

    def index(self, now: float) -> int:
        """The ghost's step: the rollout played at real time, looping."""
        return int((now - self.received) / self.dt) % len(self.hands)


def trail_segments(rollout: Rollout) -> tuple[np.ndarray, np.ndarray]:
    """(N,2,3) segments of the wrists', fingertips' and objects' predicted paths and their colours."""
    segs, colors = [], []
    for h, name in enumerate(("left", "right")):
        path = rollout.hands[:, h, list(TRAIL_POINTS)]  # (T,P,3)
        s = np.stack([path[:-1], path[1:]], axis=2).reshape(-1, 2, 3)
        segs.append(s)
        colors.append(np.broadcast_to(np.array(ghost(view.HAND_COLORS[name]), np.uint8), s.shape))
    path = rollout.objects
    s = np.stack([path[:-1], path[1:]], axis=2).reshape(-1, 2, 3)
    segs.append(s)
    colors.append(np.broadcast_to(np.array(ghost((40, 40, 40)), np.uint8), s.shape))
    return np.concatenate(segs).astype(np.float32), np.concatenate(colors).copy()


def scene_request(scene: Any) -> dict:
    """A Scene message -> the ``start`` of ``@cmd/simulate`` (an empty hand mask: all observed)."""
    mask = list(scene.hand_mask) or [1] * (2 * KEYPOINTS_PER_HAND)
    return {"hands": np.asarray(scene.hand_keypoints, float).tolist(), "hand_mask": [int(m) for m in mask],
            "objects": np.asarray(scene.object_keypoints, float).tolist(),
            "object_mask": [int(m) for m in scene.object_mask]}


class NeuralSim:
    """``query(key, request, timeout)`` a blocking Zenoh query; ``reviewed_scene()`` the Scene message
    at the review's scrubber, or None; ``count`` the @health error counter."""

    def __init__(self, server: viser.ViserServer, query: Callable[[str, dict, float], list[dict]],
                 reviewed_scene: Callable[[], Any], count: Callable[[str], None]) -> None:
        self.server = server
        self.query = query
        self.reviewed_scene = reviewed_scene
        self.count = count
        self.models: dict[str, str] = {}  # model name -> checkpoint
        self.rollout: Rollout | None = None  # the newest reply, drawn by the event loop
        self.drawn: Rollout | None = None
        self._shown: tuple[Rollout | None, int] = (None, -1)  # the rollout and step the ghost shows
        self.runs = 0
        self.problem = ""
        self._asked = threading.Event()  # Simulate pressed
        self._stop = threading.Event()
        self._build()
        self._thread = threading.Thread(target=self._work, name="panel-neural-sim", daemon=True)
        self._thread.start()

    def _build(self) -> None:
        gui, sc = self.server.gui, self.server.scene
        with gui.add_folder("Neural simulation"):
            gui.add_markdown("Rolls a network out from a scene in the policy service and draws its prediction as "
                             "a ghost: trails of the wrists, fingertips and objects, and the hands moving along them.")
            self.network = gui.add_dropdown("network", (SERVED,), initial_value=SERVED)
            self.source = gui.add_dropdown("start from", (LIVE, REVIEWED), initial_value=LIVE)
            self.seconds = gui.add_number("seconds", initial_value=3.0, min=0.2, max=20.0, step=0.1)
            gui.add_button("Simulate", color="violet").on_click(lambda _e: self._asked.set())
            self.follow = gui.add_checkbox("follow the live scene", initial_value=False,
                                           hint=f"simulate again every {FOLLOW_S:g} s from the live scene")
            self.result_md = gui.add_markdown("no simulation yet")
            self.tactile_image = gui.add_image(view.tactile_image(np.zeros(12), rows=2, cols=6, scale=24),
                                               label="predicted tactile (left, right)", format="png")
            gui.add_button("Clear the ghost").on_click(lambda _e: self._clear())
        self.trails = sc.add_line_segments("/neural/trails", np.zeros((1, 2, 3)), (200, 200, 200), thickness=0.002,
                                           visible=False)
        self.hands = {h: sc.add_line_segments(f"/neural/{h}", np.zeros((20, 2, 3)), ghost(view.HAND_COLORS[h]),
                                              thickness=0.004, visible=False) for h in ("left", "right")}
        self.objects = sc.add_point_cloud("/neural/objects", np.zeros((1, 3)), ghost((40, 40, 40)), point_size=0.012,
                                          point_shape="circle", visible=False)

    def set_models(self, models: list[Model]) -> None:
        """Monitor thread: the trained models to choose from besides the served network."""
        self.models = {m.name: str(m.checkpoint.resolve()) for m in models}
        options = (SERVED, *self.models)
        if tuple(self.network.options) != options:
            self.network.options = options
            if self.network.value not in options:
                self.network.value = SERVED

    # --- the folder's thread ------------------------------------------------------------------
    def _work(self) -> None:
        last = -np.inf
        while not self._stop.is_set():
            asked = self._asked.wait(0.1)
            following = self.follow.value and time.monotonic() - last >= FOLLOW_S
            if not (asked or following):
                continue
            self._asked.clear()
            last = time.monotonic()
            try:
                self._simulate(LIVE if following and not asked else self.source.value)
            except Exception as exc:  # the folder must keep its thread; say what went wrong
                self.count("neural_sim_error")
                self._say(f"**error**: {type(exc).__name__}: {exc}")
                log.warning("neural simulation: %r", exc, exc_info=exc)

    def _simulate(self, source: str) -> None:
        request: dict = {"seconds": float(self.seconds.value)}
        if self.network.value != SERVED:
            request["checkpoint"] = self.models.get(self.network.value, self.network.value)
        if source == REVIEWED:
            scene = self.reviewed_scene()
            if scene is None:
                self.count("neural_sim_refused")
                self._say("**refused**: no demonstration is being reviewed (Library: Review), or it has no scene")
                return
            request["start"] = scene_request(scene)
        replies = self.query(SIMULATE, request, TIMEOUT_S)
        if not replies:
            self.count("neural_sim_refused")
            self._say("**error**: no policy service answered `xm/policy/main/@cmd/simulate`")
            return
        reply = replies[0]
        if not reply.get("ok"):
            self.count("neural_sim_refused")
            self._say(f"**refused**: {reply.get('error', 'no reason given')}")
            return
        self.rollout = Rollout.from_reply(reply, source, time.monotonic())
        self.runs += 1
        r = self.rollout
        self._say(f"**{r.policy}** from {source}: {len(r.hands)} steps of {r.dt * 1e3:.0f} ms "
                  f"({(len(r.hands) - 1) * r.dt:.1f} s)" + ("" if r.tactile_predicted else "; this network predicts "
                                                             "no tactile"))

    def _say(self, text: str) -> None:
        self.problem = text if text.startswith("**") else ""
        if self.result_md.content != text:
            self.result_md.content = text

    def _clear(self) -> None:
        self.follow.value = False
        self.rollout = None

    # --- event loop ---------------------------------------------------------------------------
    def tick(self, now: float) -> None:
        """Draws the newest rollout's trails once and its ghost at the current step."""
        r = self.rollout
        if r is not self.drawn:
            self.drawn = r
            visible = r is not None
            if visible:
                self.trails.points, self.trails.colors = trail_segments(r)
            self.trails.visible = visible
            for handle in (*self.hands.values(), self.objects):
                handle.visible = visible
        if r is None:
            return
        i = r.index(now)
        if r is self._shown[0] and i == self._shown[1]:
            return
        self._shown = (r, i)
        for h, name in enumerate(("left", "right")):
            self.hands[name].points = view.hand_segments(r.hands[i, h])[0].astype(np.float32)
        if r.objects.shape[1]:
            self.objects.points = r.objects[i]
        self.tactile_image.image = view.tactile_image(r.tactile[i].ravel(), rows=2, cols=r.tactile.shape[2],
                                                      vmax=TACTILE_VMAX, scale=24)

    def health(self) -> dict:
        r = self.rollout
        return {"neural_sim": {"runs": self.runs, "problem": self.problem,
                               "shown": None if r is None else {"policy": r.policy, "steps": len(r.hands),
                                                                "source": r.source}}}

    def close(self) -> None:
        self._stop.set()
