"""policy node: publish keypoint plans over a horizon at a fixed rate from the latest scene.

``method = "learned"`` (the default deployment): the chapter-7 network from a checkpoint written by
`xm train`, stepped at its own sample rate (observed points replace predicted ones as scenes
arrive; between scenes it runs on its own predictions, the interactive neural simulation of
7.6.1) and rolled out over the horizon for every plan. ``method = "naive"``: the thesis's baseline
(10), the nearest training demonstration replayed time-aligned; its demonstrations are the ones
`xm train` saves beside the checkpoint (``demos``: a folder of Demo .npz files). A missing or
unloadable checkpoint falls back to naive and says so in @health; without demonstrations to replay
the fallback holds: it publishes the observed hands standing still over the horizon, and says so.
A missing checkpoint is watched for (``WATCH_S``): the dashboard trains the first network of a fresh
install into that path (its demonstrations first, the checkpoint last in one rename), and the node
replays the demonstrations once they appear and serves the network once it appears.
A NaN output is counted and never published. Loading the network is off the start path, so a
restarted policy plans again at once: the checkpoint and the compiled horizon load in a worker
thread while the node serves the naive replay (or holds) with status "warming".

``@cmd/serve {"checkpoint": PATH}`` (the dashboard's model list) loads another checkpoint the same
way, in the worker thread, while the current method keeps planning; the node switches to it once
it has loaded (its demonstrations become the naive fallback's). A checkpoint that does not load
leaves the current method serving and the reply of a later ``@cmd/serve {}`` says why.

``@cmd/simulate {"seconds": S, "checkpoint": PATH, "start": SCENE}`` (the dashboard's neural
simulation) rolls a checkpoint (default: the served one) out from the latest observed scene or a
given one, in a worker thread (simulation.py), and replies the predicted hands, objects and tactile.
"""

from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from services.policy.compiled import warm
from services.policy.flat_state import HAND_DIMS, BaselineError
from services.policy.model import PolicyError
from services.policy.naive import NaiveReplay
from services.policy.runner import PolicyInputError, PolicyRunner, SceneObs
from services.policy.simulation import Simulator, scene_from_request
from shared import msgs
from shared.demo import HAND_NAMES, KEYPOINTS_PER_HAND, Demo
from shared.runtime import Node

HAND_POINT_NAMES = [f"{h}/{k}" for h in HAND_NAMES for k in range(KEYPOINTS_PER_HAND)]
WATCH_S = 2.0  # how often a missing checkpoint (and its demonstrations) is looked for
MAX_CATCH_UP = 25  # policy steps run for ticks the clock skipped (0.5 s at 50 Hz); a longer stall is not caught up


def policy_steps(t: float, last_t: float | None, dt: float, cap: int = MAX_CATCH_UP) -> int:
    """Policy steps due at tick time ``t`` when the last step ran at ``last_t``: one per sample
    period elapsed (the clock skips ticks when the process is late, and the memory must still
    advance with time), at least one, at most ``cap``."""
    if last_t is None:
        return 1
    return int(min(cap, max(1, round((t - last_t) / dt))))


class PolicyService:
    @dataclass
    class Params:
        method: str = "naive"  # naive | learned
        checkpoint: str = "runs/policy/policy.pt"  # learned: written by `xm train` (`make policy`)
        rate_hz: float = 10.0  # plans per second
        horizon_s: float = 1.0
        plan_dt: float = 0.1  # naive: sample spacing of the plan (learned: the network's own dt)
        demos: str = ""  # naive: folder of Demo .npz files to replay ("": the checkpoint's folder's demos/)

    def __init__(self, node: Node, params: Params) -> None:
        if params.method not in ("naive", "learned"):
            raise ValueError(f"policy method {params.method!r}: use 'learned' or 'naive'")
        self.node = node
        self.p = params
        self.runner: PolicyRunner | None = None
        self.fallback: list[str] = []  # why the node serves less than it was asked to (@health)
        self.checkpoint: Path | None = None  # set while a checkpoint is to be loaded
        self.served: Path | None = None  # the checkpoint of ``runner``
        self.waiting_for: Path | None = None  # a checkpoint to serve once it appears
        self._watched = 0.0  # monotonic time of the last look for it
        self._refused: float | None = None  # mtime of the awaited file when it last failed to load
        self.demos = Path(params.demos) if params.demos else Path(params.checkpoint).parent / "demos"
        if params.method == "learned":
            path = Path(params.checkpoint)
            if path.exists():
                self.checkpoint = path
            else:
                self.waiting_for = path
                self.fallback.append(f"no policy checkpoint at {path} yet: serving the naive baseline until it "
                                     f"appears (the dashboard trains the first network; `make policy` does too)")
        self.naive = self._load_naive(self.demos)
        if self.checkpoint is not None:
            node.set_status("warming", f"loading {self.checkpoint}; serving the naive baseline meanwhile")
        elif self.fallback:
            node.set_status("degraded", "; ".join(self.fallback))
        self.scene = None
        self.fresh_scene = False
        self.episode: tuple[int | None, float] | None = None  # (demo index, start time)
        self.loading: asyncio.Future | None = None  # a checkpoint being loaded in the worker thread
        self.load_problem = ""  # why the last requested checkpoint is not served
        self.pub = node.output("plan")
        node.queryable("serve", self.cmd_serve)
        self.simulator = Simulator()
        node.queryable("simulate", self.cmd_simulate)
        node.health_extra = lambda: {"method": self.method_name, "checkpoint": self.serving,
                                     "loading": None if self.loading is None else str(self.checkpoint),
                                     "load_problem": self.load_problem,
                                     "waiting_for": None if self.waiting_for is None else str(self.waiting_for)}
        node.input("scene", self.on_scene)
        node.input("session", self.on_session)
        node.clock.on_jump(self.on_clock_jump)

    def on_clock_jump(self, _old: float, _new: float) -> None:
        """The world restarted: its scene and episode belong to the old timeline."""
        self.scene, self.fresh_scene, self.episode = None, False, None
        if self.naive is not None:
            self.naive.chosen = None
        if self.runner is not None:
            self.runner.reset()

    @staticmethod
    def _load_runner(path: Path) -> tuple[PolicyRunner | None, str]:
        """Worker thread: (the runner, "") or (None, why it is unusable)."""
        try:
            torch.set_num_threads(1)  # one step is small; threads would fight the simulation for cores
            warm()  # the compiled horizon: from numba's cache, or compiled now rather than inside the plan loop
            return PolicyRunner.from_checkpoint(path), ""
        except Exception as exc:  # torch raises unrelated types (UnpicklingError, ...) for files that are no checkpoint
            return None, f"policy checkpoint {path} unusable ({type(exc).__name__}: {str(exc)[:200]})"

    def _load_naive(self, folder: Path) -> NaiveReplay | None:
        """The naive replay over the demonstrations in ``folder``; None (hold) where there are none."""
        files = sorted(folder.glob("*.npz")) if folder.is_dir() else []
        try:
            naive = NaiveReplay()
            naive.fit([Demo.load(f) for f in files])
            return naive
        except (BaselineError, OSError, KeyError, ValueError) as exc:
            self.fallback.append(f"no demonstrations to replay in {folder} ({exc}): holding the observed hands")
            return None

    @property
    def method_name(self) -> str:
        if self.runner is not None:
            return f"learned:{self.runner.model.name}"
        return "naive" if self.naive is not None else "hold"

    def on_scene(self, msg) -> None:
        self.scene = msg
        self.fresh_scene = True

    def on_session(self, msg) -> None:
        if self.episode is not None and self.episode[0] is None:  # begun from a scene: its time stands
            self.episode = (msg.demo, self.episode[1])
            return
        if self.episode is None or self.episode[0] != msg.demo:
            self.episode = (msg.demo, msgs.stamp_seconds(msg.header.stamp))
            if self.naive is not None:
                self.naive.chosen = None
            if self.runner is not None:
                self.runner.reset()

    @property
    def serving(self) -> str | None:
        """The checkpoint whose network plans, or None."""
        return None if self.runner is None else str(self.served)

    def cmd_serve(self, req: dict) -> dict:
        """Load ``checkpoint`` and serve it once loaded; without one, report what is served."""
        path = req.get("checkpoint")
        if path is None:
            return {"ok": True, "method": self.method_name, "checkpoint": self.serving,
                    "loading": None if self.loading is None else str(self.checkpoint), "problem": self.load_problem}
        if not isinstance(path, str) or not Path(path).is_file():
            raise ValueError(f"checkpoint {path!r} is not a file")
        if self.loading is not None:
            raise ValueError(f"still loading {self.checkpoint}; ask again once it serves")
        self.checkpoint, self.waiting_for = Path(path), None  # the teacher's choice: no longer awaits the first
        self._start_loading()
        return {"ok": True, "loading": path, "method": self.method_name}

    async def cmd_simulate(self, req: dict) -> dict:
        """A neural simulation from the latest scene (or ``start``), off the event loop."""
        path = req.get("checkpoint") or self.serving
        if not isinstance(path, str) or not path:
            raise ValueError("no checkpoint to simulate: the policy serves no network yet; name one (checkpoint)")
        if req.get("start") is not None:
            if not isinstance(req["start"], dict):
                raise ValueError("start must be a scene object (hands, hand_mask, objects, object_mask)")
            scene = scene_from_request(req["start"])
        elif self.scene is not None:
            scene = SceneObs.from_msg(self.scene)
        else:
            raise ValueError("no scene observed yet to start from; give one (start)")
        seconds = req.get("seconds", 3.0)
        if not isinstance(seconds, (int, float)) or isinstance(seconds, bool):
            raise ValueError(f"seconds must be a number, got {seconds!r}")
        return await asyncio.to_thread(self.simulator.rollout, Path(path), scene, float(seconds))

    def _start_loading(self) -> None:
        self.load_problem = ""
        self.loading = asyncio.ensure_future(asyncio.to_thread(self._load_runner, self.checkpoint))

    def _watch(self) -> None:
        """Look for the awaited checkpoint (start loading it) and, while nothing replays, for the
        demonstrations the first network's training writes before it trains."""
        now = time.monotonic()
        if self.waiting_for is None or now - self._watched < WATCH_S:
            return
        self._watched = now
        if self.naive is None and any(self.demos.glob("*.npz")):
            self.fallback = [f for f in self.fallback if not f.startswith("no demonstrations")]
            self.naive = self._load_naive(self.demos)
            if self.naive is not None:
                self.node.log.info("replaying the demonstrations in %s until the network is ready", self.demos)
                self.node.set_status("degraded", "; ".join(self.fallback))
        if self.waiting_for.is_file() and self.loading is None and _mtime(self.waiting_for) != self._refused:
            self.checkpoint, self.waiting_for = self.waiting_for, None
            self.node.set_status("warming", f"loading {self.checkpoint}; serving the naive baseline meanwhile")
            self._start_loading()

    def _take_loaded(self) -> None:
        """The finished load: serve it, or keep serving what was served and say why."""
        runner, problem = self.loading.result()
        self.loading = None
        if runner is None:
            self.load_problem = problem
            if self.runner is None:
                self.fallback.append(f"{problem}: serving the naive baseline")
                self.node.set_status("degraded", "; ".join(self.fallback))
                if self.checkpoint == Path(self.p.checkpoint):  # (one of other configs): a new one is trained
                    self.waiting_for, self._refused = self.checkpoint, _mtime(self.checkpoint)
            return
        self.runner, self.served = runner, self.checkpoint
        naive = self._load_naive(self.checkpoint.parent / "demos")
        self.naive = naive if naive is not None else self.naive
        self.fallback = []
        self.node.set_status("ok")
        self.node.log.info("serving %s from %s", self.method_name, self.served)

    async def run(self) -> None:
        if self.checkpoint is not None:
            self._start_loading()
        while True:  # one method until a requested checkpoint has loaded, then the other
            if self.runner is None:
                await self._run_naive()
            else:
                await self._run_learned()
            if self.loading is not None and self.loading.done():
                self._take_loaded()

    async def _run_naive(self) -> None:
        steps = int(round(self.p.horizon_s / self.p.plan_dt)) + 1
        async for t in self.node.clock.ticks(self.p.rate_hz):
            self._watch()
            if self.loading is not None and self.loading.done():
                return
            if self.scene is None:
                continue
            try:
                obs = SceneObs.from_msg(self.scene)
            except ValueError as exc:  # wrong sizes: counted and skipped
                self.node.stats.count("bad_scene")
                self.node.logs.warning("bad_scene", "scene unusable", error=str(exc)[:200])
                continue
            if self.naive is None:  # hold: the observed hands, unobserved points marked so in the plan's mask
                seen = np.asarray(obs.hand_mask, bool).reshape(-1) & np.isfinite(obs.hands).all(-1).reshape(-1)
                held = np.where(seen[:, None], obs.hands.reshape(-1, 3), 0.0)
                self._publish(t, np.repeat(held[None], steps, axis=0), HAND_POINT_NAMES, self.p.plan_dt,
                              np.repeat(seen[None], steps, axis=0))
                continue
            if self.episode is None:
                # A restarted policy replays from its first scene rather than wait up to a second
                # for the world's session message; the session adopts this start (on_session).
                self.episode = (None, t)
            hands = np.where(obs.hand_mask[..., None], obs.hands, np.nan).reshape(1, -1)
            objects = np.where(obs.object_mask[:, None], obs.objects, np.nan).reshape(1, -1)
            try:
                flat = self.naive.plan(np.concatenate([hands, objects], axis=1), t - self.episode[1], steps,
                                       self.p.plan_dt)
            except BaselineError as exc:  # a scene of another object list than the demonstrations'
                self.node.stats.count("bad_scene")
                self.node.logs.warning("bad_scene", "scene unusable for the naive replay", error=str(exc)[:200])
                continue
            self._publish(t, flat[:, :HAND_DIMS].reshape(steps, -1, 3), HAND_POINT_NAMES, self.p.plan_dt)

    async def _run_learned(self) -> None:
        runner = self.runner
        dt = runner.model.dt
        plan_every = 1.0 / self.p.rate_hz - 0.5 * dt  # sim seconds between plans (ticks may be skipped)
        steps = max(2, int(round(self.p.horizon_s / dt)))
        names = HAND_POINT_NAMES + [f"object/{n}" for n in runner.model.object_names]
        last_plan, last_step = -np.inf, None
        async for t in self.node.clock.ticks(1.0 / dt):
            if self.loading is not None and self.loading.done():
                return
            if self.scene is None:
                continue
            try:
                obs = SceneObs.from_msg(self.scene) if self.fresh_scene or runner.state is None else None
                self.fresh_scene = False
                missed = policy_steps(t, last_step, dt) - 1 if runner.state is not None else 0
                last_step = t
                for _ in range(missed):  # the skipped ticks, on the policy's own prediction
                    runner.step(None)
                if missed:
                    self.node.stats.count("ticks_caught_up", n=missed)
                runner.step(obs)
                if t - last_plan >= plan_every or t < last_plan:  # (or the clock jumped back)
                    last_plan = t
                    self._publish(t, runner.horizon(None, steps), names, dt)
            except PolicyInputError as exc:
                self.node.stats.count("bad_scene")
                self.node.logs.warning("bad_scene", "scene unusable", error=str(exc)[:200])
                runner.reset()
            except PolicyError:
                self.node.stats.count("nan_plan")  # never let NaN reach trajopt
                runner.reset()

    def _publish(self, t: float, points: np.ndarray, names: list[str], dt: float,
                 mask: np.ndarray | None = None) -> None:
        """A Plan of ``points`` (steps, N, 3); ``mask`` (steps, N) marks the points that carry a goal
        (default all)."""
        if not np.isfinite(points).all():
            self.node.stats.count("nan_plan")
            return
        steps = len(points)
        self.pub.put(msgs.make(
            "xm_msgs/msg/Plan", header=msgs.header(t, "world"), policy=self.method_name, dt=dt, steps=steps,
            point_names=names, positions=points.astype(np.float32).ravel(),
            mask=(np.ones(points.shape[:2]) if mask is None else mask).astype(np.uint8).ravel(),
            efforts=self._efforts()))

    def _efforts(self) -> np.ndarray:
        """Predicted tactile per horizon step, hand and region (7.2.10), kPa; empty without tactile."""
        if self.runner is None or not self.runner.model.cfg.tactile:
            return np.zeros(0, np.float32)
        return np.asarray(self.runner.horizon_tactile, np.float32).ravel()


def _mtime(path: Path) -> float | None:
    try:
        return path.stat().st_mtime
    except OSError:
        return None
