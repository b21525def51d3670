"""Demonstrations as recon reconstructs them from rendered images (`xm eval --observations
reconstructed`, issue 28 deliverable 4).

Every teacher demonstration is replayed through the perception chain the live cell runs: the
simulated rig renders the seven cameras from the world's state at each demonstration sample
(services/world/render.py, the live 256x192 by default), each camera reading out the window camhub
would read around the last reconstructed hands (services/camhub/roi.py, full frames when no hand
is tracked and every ``reacquire_every``-th frame set) as a JPEG at camhub's quality; the 2-D
detector finds the keypoints (the learned U-Net on the images, or the simulated detector's
projected truth with noise, dropouts and occlusion); recon's pipeline (services/recon/pipeline.py)
triangulates them robustly and fits the hands and objects. The reconstructed hands, objects and
masks replace the truth in the demonstration; tactile stays the glove's. Reconstruction runs at
the demonstration's own rate (0.02 s): the policy is trained and scored on 0.02 s steps, so it sees
a frame set per step and no interpolation invents motion between camera frames.

Before the demonstration's first sample, recon tracks the teacher for ``lead_in`` frame sets at
the start pose (in a live session recon runs before the demonstration starts), so the start state
is a fitted scene, not recon's first cold frame. A training demonstration is reconstructed whole;
of a validation demonstration every method observes only the start state it rolls out from
(``observed_steps``), so only that is reconstructed: the rest is the truth the rollout is scored
against.

``CellObserver`` is the same chain inside the robot loop: the cell rendered at the camera rate
with the robot in it, objects reconstructed, nothing observed between frame sets.

Reconstructing a demonstration costs rendering and detection (minutes for the 15 of a protocol on
this machine), so each is cached on disk under ``cache/<key>/demo_<i>.npz``, the key naming the
seed, the detector (and a digest of its weights), the image size, the windows and a digest of the
sources that make the reconstruction (``RECON_SOURCES``).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from evaluation.runs import sources_digest
from services.camhub.camera_info import encode_jpeg
from services.camhub.roi import CameraGeometry, Roi, RoiParams, full_frame, rig_windows
from services.recon import smoothing
from services.recon.detector import CameraModel, SimulatedDetector
from services.recon.learned_detector import DEFAULT_WEIGHTS_DIR, LearnedDetector, View
from services.recon.objects import task_keypoint_names
from services.recon.pipeline import Reconstructor
from services.world.model import camera_specs
from services.world.render import SceneRenderer, Snapshot
from services.world.sim import WorldSim
from services.world.teacher import Teacher, occlusion
from shared.demo import HAND_NAMES, KEYPOINTS_PER_HAND, Demo
from shared.geometry import projection

OBSERVATIONS = ("truth", "reconstructed")
DETECTORS = ("learned", "simulated")
WINDOWS = ("roi", "full")
# the code that makes a reconstructed demonstration: a change to any of it redoes the cached ones
RECON_SOURCES = ("evaluation/reconstructed.py", "services/recon", "perception", "services/camhub",
                 "services/world", "shared/geometry.py", "shared/demo.py")


class ReconstructionError(ValueError):
    """A demonstration that cannot be reconstructed (no teacher seed, weights for another task)."""


@dataclass(frozen=True)
class ReconOptions:
    detector: str = "learned"  # "simulated": projected truth + noise + dropouts + occlusion (no images)
    weights: str = str(DEFAULT_WEIGHTS_DIR)  # the learned detector's folder (meta.json, weights.pt, model.onnx)
    width: int = 256  # the live rig's image size
    height: int = 192
    windows: str = "roi"  # "roi": camhub's windows around the last reconstructed hands; "full": whole frames
    reacquire_every: int = 10  # camhub's full-frame reacquisition period (roi windows)
    jpeg_quality: int = 80  # camhub's
    lead_in: int = 10  # frame sets of the start pose recon sees before the demonstration's first sample
    smooth: bool = True  # offline smoothing of every track (services/recon/smoothing.py), lead-in included
    pixel_noise: float = 1.0  # simulated detector
    dropout: float = 0.08
    threads: int = 1  # the learned detector's runtime threads

    def __post_init__(self) -> None:
        if self.detector not in DETECTORS:
            raise ReconstructionError(f"detector {self.detector!r}: choose one of {', '.join(DETECTORS)}")
        if self.windows not in WINDOWS:
            raise ReconstructionError(f"windows {self.windows!r}: choose one of {', '.join(WINDOWS)}")


def cache_key(seed: int, options: ReconOptions) -> str:
    """The folder name of one protocol's reconstructed demonstrations: readable fields, then a digest
    of everything that changes the result (the learned detector's weights included)."""
    fields = {k: v for k, v in asdict(options).items() if k not in ("threads", "weights")}
    fields["code"] = sources_digest(RECON_SOURCES).hexdigest()[:12]
    if options.detector == "learned":
        fields["weights"] = weights_digest(Path(options.weights))
    else:
        fields = {k: v for k, v in fields.items() if k not in ("jpeg_quality",)}
    digest = hashlib.sha256(json.dumps(fields, sort_keys=True).encode()).hexdigest()[:10]
    return f"seed{seed}-{options.detector}-{options.windows}-{options.width}x{options.height}-{digest}"


def weights_digest(folder: Path) -> str:
    """A digest of the detector's files (meta.json and the weights the runtime loads)."""
    h = hashlib.sha256()
    found = False
    for name in ("meta.json", "weights.pt", "model.onnx"):
        p = folder / name
        if p.exists():
            h.update(name.encode())
            h.update(p.read_bytes())
            found = True
    if not found:
        raise ReconstructionError(f"no detector weights in {folder}; train them with `xm detector label && "
                                  f"xm detector train`, or use --detector simulated")
    return h.hexdigest()[:16]


def rig(width: int, height: int) -> tuple[list[CameraGeometry], np.ndarray]:
    """The simulated rig's true cameras (the calibration's format: K, no distortion, world_T_cam) and
    their full-image projection matrices (C,3,4)."""
    specs = camera_specs(width, height)
    cams = [CameraGeometry(c.name, width, height, c.K, np.zeros(5), c.world_T_cam) for c in specs]
    return cams, np.stack([projection(c.K, c.world_T_cam) for c in cams])


def tracked_hands(hands: np.ndarray, mask: np.ndarray) -> np.ndarray | None:
    """The reconstructed hand keypoints camhub's windows follow (N,3), or None when none is seen."""
    pts = np.asarray(hands, float).reshape(-1, 3)[np.asarray(mask, bool).ravel()]
    return pts if len(pts) else None


def frame_windows(cams: list[CameraGeometry], hands: np.ndarray | None, trigger: int,
                  options: ReconOptions) -> list[Roi]:
    """Each camera's readout window of one frame set."""
    if options.windows == "full":
        return [full_frame(c.width, c.height) for c in cams]
    windows, _ = rig_windows(cams, hands, 0.0, trigger, RoiParams(reacquire_every=options.reacquire_every))
    return [windows[c.name] for c in cams]


def jpeg_round_trip(rgb: np.ndarray, quality: int) -> np.ndarray:
    """The image as recon decodes it from camhub's JPEG."""
    img = cv2.imdecode(np.frombuffer(encode_jpeg(rgb, quality), np.uint8), cv2.IMREAD_COLOR)
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


class DemoScenes:
    """The world's state at any instant of a protocol demonstration, as the renderer's snapshot and
    as the truth the simulated detector projects (the teacher's script, as the world applies it)."""

    def __init__(self, qpos: np.ndarray, mocap_pos: np.ndarray, mocap_quat: np.ndarray, free_adr: dict[str, int],
                 mocap_ids: np.ndarray) -> None:
        self.qpos0, self.mocap_pos, self.mocap_quat = qpos, mocap_pos, mocap_quat
        self.free_adr, self.mocap_ids = free_adr, mocap_ids

    @classmethod
    def for_task(cls, task: str, seed: int, width: int, height: int) -> DemoScenes:
        sim = WorldSim(task, seed=seed, width=width, height=height)  # the robot at home, objects' joints
        m = sim.model
        free = {b: int(m.jnt_qposadr[m.joint(f"{b}_free").id]) for b in ("board", "camera", "box", "plate")
                if _has_joint(m, f"{b}_free")}
        ids = np.array([[m.body_mocapid[m.body(f"{h}_kp{k}").id] for k in range(KEYPOINTS_PER_HAND)]
                        for h in HAND_NAMES])
        return cls(sim.data.qpos.copy(), sim.data.mocap_pos.copy(), sim.data.mocap_quat.copy(), free, ids)

    def at(self, teacher: Teacher, t: float, seed: int, demo: int, glove: str
           ) -> tuple[Snapshot, np.ndarray, np.ndarray]:
        """Snapshot, truth points (42 hand + K object, recon's order) and their visibility at ``t``."""
        st = teacher.state(t)
        qpos = self.qpos0.copy()
        for body, (pos, quat) in st.objects.items():
            adr = self.free_adr[body]
            qpos[adr:adr + 3], qpos[adr + 3:adr + 7] = pos, quat
        mocap = self.mocap_pos.copy()
        mocap[self.mocap_ids.ravel()] = st.hands.reshape(-1, 3)
        snap = Snapshot(teacher.task, float(t), qpos, mocap, self.mocap_quat.copy(), seed=seed, demo=demo,
                        glove_hand=glove)
        hv, ov = occlusion(st.hands, st.keypoints)
        return snap, np.concatenate([st.hands.reshape(-1, 3), st.keypoints]), np.concatenate([hv.ravel(), ov])


def _has_joint(model: object, name: str) -> bool:
    try:
        model.joint(name)
    except KeyError:
        return False
    return True


class DemoReconstructor:
    """Reconstructs protocol demonstrations with one detector; create and use it on one thread (the
    renderer's GL context)."""

    def __init__(self, task: str, seed: int, options: ReconOptions) -> None:
        self.task, self.seed, self.options = task, seed, options
        self.cams, self.P = rig(options.width, options.height)
        self.names = [f"{h}/{k}" for h in HAND_NAMES for k in range(KEYPOINTS_PER_HAND)] + task_keypoint_names(task)
        self.scenes = DemoScenes.for_task(task, seed, options.width, options.height)
        self.renderer = self.learned = self.simulated = None
        self.present_confidence = 0.0  # the learned detector's hand_present_confidence
        if options.detector == "learned":
            self.learned = LearnedDetector(options.weights, threads=options.threads)
            if list(self.learned.names) != self.names:
                raise ReconstructionError(f"detector weights in {options.weights} name {len(self.learned.names)} "
                                          f"keypoints, not the {len(self.names)} of task {task!r} in recon's order")
            self.renderer = SceneRenderer(task, options.width, options.height)
            self.present_confidence = self.learned.hand_present_confidence
        else:
            self.simulated = SimulatedDetector(options.pixel_noise, options.dropout, seed=seed)

    def close(self) -> None:
        if self.renderer is not None:
            self.renderer.close()

    def detect(self, snap: Snapshot, truth: np.ndarray, visible: np.ndarray, windows: list[Roi]
               ) -> tuple[np.ndarray, np.ndarray]:
        """uv (C,N,2) full-image pixels and confidence (C,N) of one frame set."""
        models = [CameraModel(P, c.width, c.height, tuple(w)) for P, c, w in zip(self.P, self.cams, windows,
                                                                                   strict=True)]
        if self.learned is None:
            uv, seen = self.simulated.detect(models, truth, visible)
            return uv, seen.astype(float)
        images = self.renderer.render(snap, [tuple(w) for w in windows])
        views = [View(c.name, m, jpeg_round_trip(img, self.options.jpeg_quality))
                 for c, m, img in zip(self.cams, models, images, strict=True)]
        return self.learned.detect(views)

    def demo(self, demo: Demo, steps: int | None = None) -> Demo:
        """The first ``steps`` samples of ``demo`` (all by default) with hands, objects and masks as
        recon reconstructs them (tactile unchanged)."""
        steps = demo.steps if steps is None else max(1, min(int(steps), demo.steps))
        meta = demo.meta
        if "seed" not in meta or "demo" not in meta:
            raise ReconstructionError("only teacher demonstrations (meta 'seed' and 'demo') can be re-rendered")
        if list(demo.object_names) != self.names[2 * KEYPOINTS_PER_HAND:]:
            raise ReconstructionError(f"demonstration objects {demo.object_names} are not task {self.task!r}'s")
        teacher = Teacher(self.task, int(meta["seed"]), meta.get("grasp_hand"), meta.get("tactile_hand"))
        glove = str(meta.get("tactile_hand", ""))
        recon = Reconstructor(self.task, hand_present_confidence=self.present_confidence)
        if self.learned is not None:
            self.learned.reset()  # another layout: no object's detections carry over
        hands, hmask, objs, omask = [], [], [], []
        tracked = None
        times = [0.0] * self.options.lead_in + [k * demo.dt for k in range(steps)]
        for trigger, t in enumerate(times):
            snap, truth, visible = self.scenes.at(teacher, t, self.seed, int(meta["demo"]), glove)
            windows = frame_windows(self.cams, tracked, trigger, self.options)
            uv, conf = self.detect(snap, truth, visible, windows)
            r = recon.step(self.P, uv, conf, np.array([tuple(w) for w in windows], float))
            tracked = tracked_hands(r.hands, r.hand_mask)
            hands.append(r.hands)
            hmask.append(r.hand_mask)
            objs.append(r.objects)
            omask.append(r.object_mask)
        hands_a, hmask_a = np.array(hands, float), np.array(hmask, bool)
        objs_a, omask_a = np.array(objs, float), np.array(omask, bool)
        if self.options.smooth:  # over the lead-in too: a start state is smoothed from its past only
            hands_a, hmask_a = smoothing.smooth_tracks(hands_a, hmask_a, demo.dt, smoothing.HANDS)
            objs_a, omask_a = smoothing.smooth_tracks(objs_a, omask_a, demo.dt, smoothing.OBJECTS)
        lead = self.options.lead_in
        hands_a = np.nan_to_num(hands_a[lead:]).astype(np.float32)
        objs_a = np.nan_to_num(objs_a[lead:]).astype(np.float32)
        hmask_a, omask_a = hmask_a[lead:].astype(np.uint8), omask_a[lead:].astype(np.uint8)
        hands_a *= hmask_a[..., None]  # masked points are zero, never NaN (as in recon's scene)
        objs_a *= omask_a[..., None]
        return replace(demo, hands=hands_a, hand_mask=hmask_a, objects=objs_a, object_mask=omask_a,
                       tactile=demo.tactile[:steps], tactile_mask=demo.tactile_mask[:steps], phase=demo.phase[:steps],
                       meta={**meta, "observations": f"reconstructed:{self.options.detector}:{self.options.windows}"})


class CellObserver:
    """The robot loop's view of the objects (`xm eval --execute --observations reconstructed`): at
    the camera rate (``period_s``) the rig renders the cell as it is (the robot included) and recon
    reconstructs it; between frame sets nothing new is observed. ``objects`` holds each keypoint
    where it was last reconstructed (what the contact anchors aim at), ``mask`` what the latest
    frame set saw."""

    def __init__(self, task: str, seed: int, demo: int, options: ReconOptions, period_s: float = 0.2) -> None:
        self.worker = DemoReconstructor(task, seed, options)
        self.recon = Reconstructor(task, hand_present_confidence=self.worker.present_confidence)
        self.demo, self.period_s = demo, period_s
        n = len(self.worker.names) - 2 * KEYPOINTS_PER_HAND
        self.objects, self.mask = np.zeros((n, 3)), np.zeros(n, bool)
        self.next_t, self.trigger, self.tracked = -np.inf, 0, None
        self.frame_sets = 0

    def close(self) -> None:
        self.worker.close()

    def frame_set(self, sim: WorldSim) -> None:
        """Reconstructs one frame set of the cell as ``sim`` holds it now."""
        snap = Snapshot(sim.task, sim.time, sim.data.qpos.copy(), sim.data.mocap_pos.copy(),
                        sim.data.mocap_quat.copy(), robot=sim.robot_name, seed=self.worker.seed, demo=self.demo)
        hands = sim.hand_keypoints()
        _, objects = sim.object_keypoints()
        visible = np.r_[np.zeros(hands.size // 3), np.ones(len(objects))]  # the hands have left the cell
        windows = frame_windows(self.worker.cams, self.tracked, self.trigger, self.worker.options)
        uv, conf = self.worker.detect(snap, np.concatenate([hands.reshape(-1, 3), objects]), visible, windows)
        r = self.recon.step(self.worker.P, uv, conf)
        self.tracked = tracked_hands(r.hands, r.hand_mask)
        seen = r.object_mask.astype(bool)
        self.objects[seen] = r.objects[seen]
        self.mask = seen
        self.trigger += 1
        self.frame_sets += 1

    def update(self, sim: WorldSim) -> bool:
        """Takes a frame set when one is due at the sim's time; True when it did."""
        if sim.time + 1e-9 < self.next_t:
            return False
        self.frame_set(sim)
        self.next_t = max(self.next_t + self.period_s, sim.time) if np.isfinite(self.next_t) else \
            sim.time + self.period_s
        return True


def observed_steps(demo: Demo) -> int:
    """How much of a protocol demonstration a method observes: a training demonstration whole, a
    validation demonstration only its start state (every method rolls out from it; the rest of it
    is the truth the rollout is scored against)."""
    return demo.steps if demo.meta.get("split") == "train" else 1


def reconstructed_demos(demos: list[Demo], task: str, seed: int, options: ReconOptions,
                        cache: str | Path | None = "runs/recon_demos", progress: bool = True,
                        steps: list[int] | None = None) -> list[Demo]:
    """``demos`` (a protocol of ``seed``) as recon reconstructs them, the i-th over its first
    ``steps[i]`` samples (default ``observed_steps``), from ``cache`` where present; the split and
    every other meta field are kept."""
    steps = [observed_steps(d) for d in demos] if steps is None else list(steps)
    folder = Path(cache) / cache_key(seed, options) if cache else None
    out: list[Demo | None] = [None] * len(demos)
    if folder is not None:
        for i, d in enumerate(demos):
            path = folder / f"demo_{i:03d}.npz"
            if path.exists():
                cached = Demo.load(path)
                if cached.steps >= steps[i] and cached.meta.get("seed") == d.meta.get("seed"):
                    out[i] = truncated(cached, steps[i])
    todo = [i for i, d in enumerate(out) if d is None]
    if todo:
        worker = DemoReconstructor(task, seed, options)
        try:
            for i in tqdm(todo, desc=f"reconstruct ({options.detector})", disable=not progress):
                out[i] = worker.demo(demos[i], steps[i])
                if folder is not None:
                    folder.mkdir(parents=True, exist_ok=True)
                    out[i].save(folder / f"demo_{i:03d}.npz")
        finally:
            worker.close()
    return [replace(r, meta={**r.meta, "split": d.meta.get("split")}) for r, d in zip(out, demos, strict=True)]


def truncated(demo: Demo, steps: int) -> Demo:
    """The first ``steps`` samples of a demonstration."""
    if steps >= demo.steps:
        return demo
    return replace(demo, hands=demo.hands[:steps], hand_mask=demo.hand_mask[:steps], objects=demo.objects[:steps],
                   object_mask=demo.object_mask[:steps], tactile=demo.tactile[:steps],
                   tactile_mask=demo.tactile_mask[:steps], phase=demo.phase[:steps])


def held_objects(demo: Demo, smooth: int = 9) -> Demo:
    """The demonstration with every masked object point held where it was last seen (first seen,
    before that) and each point's track median-filtered over ``smooth`` samples: what the contact
    anchors are mined from, as they need every point at every sample and a resting object at rest."""
    objs, mask = demo.objects.astype(float).copy(), demo.object_mask.astype(bool)
    for k in range(objs.shape[1]):
        seen = np.flatnonzero(mask[:, k])
        if not len(seen):
            continue
        last = seen[np.clip(np.searchsorted(seen, np.arange(len(objs)), side="right") - 1, 0, len(seen) - 1)]
        objs[:, k] = objs[last, k]
    half = smooth // 2
    padded = np.concatenate([np.repeat(objs[:1], half, 0), objs, np.repeat(objs[-1:], half, 0)])
    windows = np.lib.stride_tricks.sliding_window_view(padded, smooth, axis=0)  # (T,K,3,smooth)
    return replace(demo, objects=np.median(windows, axis=-1).astype(np.float32),
                   object_mask=np.ones_like(demo.object_mask))


def reconstruction_error(recon: Demo, truth: Demo) -> dict[str, float]:
    """Mean keypoint error (m) of a reconstructed demonstration against its truth where reported,
    and the fraction reported, for hands and objects."""
    truth = truncated(truth, recon.steps)
    hm, om = recon.hand_mask.astype(bool), recon.object_mask.astype(bool)
    eh = np.linalg.norm(recon.hands - truth.hands, axis=-1)[hm]
    eo = np.linalg.norm(recon.objects - truth.objects, axis=-1)[om]
    return {"hand_m": float(eh.mean()) if eh.size else float("nan"),
            "object_m": float(eo.mean()) if eo.size else float("nan"),
            "hand_reported": float(hm.mean()), "object_reported": float(om.mean())}
