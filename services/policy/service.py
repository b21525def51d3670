"""policy node: publish keypoint plans over a horizon at a fixed rate from the latest scene.

``method = "learned"`` (the default deployment): the chapter-7 network from a checkpoint written by
`xm train`, stepped at its own sample rate (observed points replace predicted ones as scenes
arrive; between scenes it runs on its own predictions, the interactive neural simulation of
7.6.1) and rolled out over the horizon for every plan. ``method = "naive"``: the thesis's baseline
(10), the nearest training demonstration replayed time-aligned. A missing or unloadable
checkpoint falls back to naive and says so in @health; a NaN output is counted and never
published. Loading is off the start path, so a restarted policy plans again at once: the naive
demonstrations and the checkpoint (torch, the compiled horizon) load in worker threads, and the
learned policy serves the naive baseline with status "warming" until its network is ready.
"""

from __future__ import annotations

import asyncio
import hashlib
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from services.policy.naive import NaiveReplay
from services.world.teacher import generate_demo
from shared import msgs
from shared.demo import HAND_NAMES, KEYPOINTS_PER_HAND, Demo
from shared.runtime import Node, latest

HAND_POINT_NAMES = [f"{h}/{k}" for h in HAND_NAMES for k in range(KEYPOINTS_PER_HAND)]
# The naive replay's teacher demonstrations take seconds to simulate; a restarted policy reads them
# from here. The file name carries a digest of the simulation's source, so a changed teacher or
# world never serves stale demonstrations.
DEMO_CACHE = Path(os.environ.get("XM_CACHE_DIR", Path.home() / ".cache" / "crossmodal")) / "demos"
DEMO_SOURCES = [Path(__file__).resolve().parents[1] / "world", Path(__file__).resolve().parents[2] / "shared"]


def source_digest() -> str:
    """A short digest of the Python sources the teacher's demonstrations depend on."""
    h = hashlib.sha256()
    for root in DEMO_SOURCES:
        for path in sorted(root.rglob("*.py")):
            h.update(path.read_bytes())
    return h.hexdigest()[:16]


def teacher_demos(task: str, seeds: tuple[int, ...], cache: Path = DEMO_CACHE) -> list[Demo]:
    """The teacher's demonstrations of ``task`` for ``seeds``, cached on disk (a cache that cannot
    be written is skipped: the demonstrations are simulated every time)."""
    digest = source_digest()
    demos = []
    for i, seed in enumerate(seeds):
        path = cache / f"{task}-{seed}-{i}-{digest}.npz"
        try:
            demos.append(Demo.load(path))
            continue
        except (OSError, ValueError, KeyError):
            pass
        demo = generate_demo(task, seed, index=i)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_name(f".{path.stem}.{os.getpid()}.npz")
            demo.save(tmp)
            os.replace(tmp, path)  # whole or not at all: another policy may read it at the same time
        except OSError:
            pass
        demos.append(demo)
    return demos
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
        task: str = "assembly"
        train_seeds: tuple[int, ...] = (9000, 9001, 9002)  # teacher demos the naive replay draws from

    def __init__(self, node: Node, params: Params) -> None:
        if params.method not in ("naive", "learned"):
            raise ValueError(f"policy method {params.method!r}: use 'learned' or 'naive'")
        self.node = node
        self.p = params
        self.runner = None
        self.checkpoint: Path | None = None  # set while a checkpoint is to be loaded
        if params.method == "learned":
            path = Path(params.checkpoint)
            if path.exists():
                self.checkpoint = path
                node.set_status("warming", f"loading {path}; serving the naive baseline meanwhile")
            else:
                node.set_status("degraded", f"no policy checkpoint at {path}: serving the naive baseline; "
                                f"train one with `make policy`")
        self.naive = NaiveReplay()
        self.scene = None
        self.fresh_scene = False
        self.episode: tuple[int, float] | None = None  # (demo index, start time)
        self.pub = node.publisher("xm/policy/main/plan")
        node.subscribe("xm/recon/main/scene", self.on_scene, latest(1))
        node.subscribe("xm/world/sim/session", self.on_session, latest(1))
        node.clock.on_jump(self.on_clock_jump)

    def on_clock_jump(self, _old: float, _new: float) -> None:
        """The world restarted: its scene and episode belong to the old timeline."""
        self.scene, self.fresh_scene, self.episode = None, False, None
        self.naive.chosen = None
        if self.runner is not None:
            self.runner.reset()

    def _fit_naive(self) -> None:
        """Worker thread: the teacher demonstrations the naive replay draws from."""
        self.naive.fit(teacher_demos(self.p.task, tuple(self.p.train_seeds)))

    @staticmethod
    def _load_runner(path: Path) -> tuple[object | None, str]:
        """Worker thread: (the runner, "") or (None, why it is unusable)."""
        # torch and the policy package are heavy and only needed with a checkpoint: imported here.
        from services.policy.ours import PolicyError
        from services.policy.simulate import PolicyRunner

        try:
            import torch

            from services.policy.compiled import warm

            torch.set_num_threads(1)  # one step is small; threads would fight the simulation for cores
            warm()  # the compiled horizon: from numba's cache, or compiled now rather than inside the plan loop
            return PolicyRunner.from_checkpoint(path), ""
        except (PolicyError, OSError, RuntimeError, KeyError, ValueError) as exc:
            return None, f"policy checkpoint {path} unusable ({exc}): serving the naive baseline"

    @property
    def method_name(self) -> str:
        return f"learned:{self.runner.model.cfg.name}" if self.runner is not None else "naive"

    def on_scene(self, msg) -> None:
        self.scene = msg
        self.fresh_scene = True

    def on_session(self, msg) -> None:
        if self.episode is None or self.episode[0] != msg.demo:
            self.episode = (msg.demo, msgs.stamp_seconds(msg.header.stamp))
            self.naive.chosen = None
            if self.runner is not None:
                self.runner.reset()

    async def run(self) -> None:
        loading = None
        if self.checkpoint is not None:
            loading = asyncio.ensure_future(asyncio.to_thread(self._load_runner, self.checkpoint))
        await asyncio.to_thread(self._fit_naive)
        if loading is not None:
            await self._run_naive(until=loading)
            self.runner, problem = loading.result()
            if self.runner is None:
                self.node.set_status("degraded", problem)
            else:
                self.node.set_status("ok")
                self.node.log.info("serving %s", self.method_name)
                await self._run_learned()
        await self._run_naive()

    async def _run_naive(self, until: asyncio.Future | None = None) -> None:
        steps = int(round(self.p.horizon_s / self.p.plan_dt)) + 1
        async for t in self.node.clock.ticks(self.p.rate_hz):
            if until is not None and until.done():
                return
            if self.scene is None or self.episode is None:
                continue
            if self.naive.chosen is None:
                objects = np.asarray(self.scene.object_keypoints, float).reshape(-1, 3)
                self.naive.start(objects, np.asarray(self.scene.object_mask, bool))
            hands, _ = self.naive.plan(t - self.episode[1], steps, self.p.plan_dt)
            self._publish(t, hands.reshape(steps, -1, 3), HAND_POINT_NAMES, self.p.plan_dt)

    async def _run_learned(self) -> None:
        from services.policy.ours import PolicyError
        from services.policy.simulate import PolicyInputError, SceneObs

        runner = self.runner
        dt = runner.model.dt
        plan_every = 1.0 / self.p.rate_hz - 0.5 * dt  # sim seconds between plans (ticks may be skipped)
        steps = max(2, int(round(self.p.horizon_s / dt)))
        names = HAND_POINT_NAMES + [f"object/{n}" for n in runner.model.object_names]
        last_plan, last_step = -np.inf, None
        async for t in self.node.clock.ticks(1.0 / dt):
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

    def _publish(self, t: float, points: np.ndarray, names: list[str], dt: float) -> None:
        if not np.isfinite(points).all():
            self.node.stats.count("nan_plan")
            return
        steps = len(points)
        self.pub.put(msgs.make(
            "xm_msgs/msg/Plan", header=msgs.header(t, "world"), policy=self.method_name, dt=dt, steps=steps,
            point_names=names, positions=points.astype(np.float32).ravel(),
            mask=np.ones(points.shape[:2], np.uint8).ravel(), efforts=self._efforts()))

    def _efforts(self) -> np.ndarray:
        """Predicted tactile per horizon step, hand and region (7.2.10), kPa; empty without tactile."""
        if self.runner is None or not self.runner.model.cfg.tactile:
            return np.zeros(0, np.float32)
        return np.asarray(self.runner.horizon_tactile, np.float32).ravel()
