"""Demonstrations -> training arrays of the chapter-7 policy (pure numpy, no I/O but the MCAP reader).

A state has P = 42 + K keypoints (left hand 21, right hand 21, then the K object points), their
velocities, per-point observed masks, tactile (2 hands x 6 regions) with its glove mask, the
reservoir activations (7.2.8) and, with a time window, its older block means. One training sample
is the step t -> t+1 of a demonstration.

Augmentation: left/right mirroring (y -> -y, hands swapped) of every demonstration, hand-swap
sampling (left-grasping samples with probability 0.6, thesis 7.6.8), rotation about gravity
(7.2.4: one angle per sample).

Recordings: ``demos_from_mcap`` splits the scene stream of an MCAP recording by the session's
demonstration label; NaN keypoints become masked, gaps end a demonstration, both are reported.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from rosbags.highlevel import AnyReader

from learning.reservoir import Reservoir
from services.policy.model import object_groups
from services.policy.window import step_windows
from shared import msgs
from shared.demo import FINGERTIPS, HAND_NAMES, KEYPOINTS_PER_HAND, TACTILE_REGIONS, Demo
from shared.recording_files import recording_segments

SCENE_KEY = "xm/recon/main/scene"
SESSION_KEY = "xm/world/sim/session"
HAND_POINTS = 2 * KEYPOINTS_PER_HAND


class DatasetError(ValueError):
    """Demonstrations that cannot be learned from; the message names the demonstration and why."""


# --- geometry ----------------------------------------------------------------------------------
def rotate_z(x: np.ndarray, angle: np.ndarray | float) -> np.ndarray:
    """Rotate vectors (..., 3) about gravity; ``angle`` broadcasts against x[..., 0]."""
    c, s = np.cos(angle), np.sin(angle)
    out = np.array(x, copy=True)
    out[..., 0] = c * x[..., 0] - s * x[..., 1]
    out[..., 1] = s * x[..., 0] + c * x[..., 1]
    return out


def velocities(x: np.ndarray, dt: float) -> np.ndarray:
    """Backward differences along axis 0, zero at the first step (what a causal observer sees)."""
    v = np.zeros_like(x)
    v[1:] = (x[1:] - x[:-1]) / dt
    return v


_SWAP = {"left": "right", "right": "left"}


def mirror(demo: Demo) -> Demo:
    """Left/right mirror image: y -> -y with the hands (and their tactile channels) swapped."""
    flip = np.array([1.0, -1.0, 1.0], np.float32)
    meta = dict(demo.meta)
    for key in ("grasp_hand", "press_hand", "tactile_hand"):
        if meta.get(key) in _SWAP:
            meta[key] = _SWAP[meta[key]]
    meta["mirrored"] = not meta.get("mirrored", False)
    return Demo(dt=demo.dt, hands=(demo.hands[:, ::-1] * flip).astype(np.float32),
                hand_mask=demo.hand_mask[:, ::-1].copy(), object_names=list(demo.object_names),
                objects=(demo.objects * flip).astype(np.float32), object_mask=demo.object_mask.copy(),
                tactile=demo.tactile[:, ::-1].copy(), tactile_mask=demo.tactile_mask[:, ::-1].copy(),
                phase=list(demo.phase), meta=meta)


def split_demos(demos: list[Demo], n_train: int = 3) -> tuple[list[Demo], list[Demo]]:
    """Train/validation by demonstration: ``meta['split']`` where present, else the first n_train."""
    if all("split" in d.meta for d in demos):
        return ([d for d in demos if d.meta["split"] == "train"],
                [d for d in demos if d.meta["split"] != "train"])
    return demos[:n_train], demos[n_train:]


# --- per-demonstration arrays ----------------------------------------------------------------
@dataclass
class DemoArrays:
    """One demonstration as flat keypoint arrays (P = 42 + K points)."""

    pos: np.ndarray  # (T,P,3)
    vel: np.ndarray  # (T,P,3) backward differences; zero where either sample is unobserved
    mask: np.ndarray  # (T,P) bool observed
    vmask: np.ndarray  # (T,P) bool velocity valid (observed now and one step before)
    tactile: np.ndarray  # (T,2,R)
    tmask: np.ndarray  # (T,2,R) bool
    left: bool  # grasping with the left hand
    dt: float
    name: str
    goal: np.ndarray | None = None  # (T,2) object body each hand acts on next (goal_bodies), -1 none

    @property
    def steps(self) -> int:
        return len(self.pos)


def demo_arrays(demo: Demo) -> DemoArrays:
    t = demo.steps
    pos = np.concatenate([demo.hands.reshape(t, -1, 3), demo.objects], axis=1).astype(np.float64)
    mask = np.concatenate([demo.hand_mask.reshape(t, -1), demo.object_mask], axis=1).astype(bool)
    mask &= np.isfinite(pos).all(-1)
    pos = np.nan_to_num(pos)
    vmask = mask.copy()
    vmask[1:] &= mask[:-1]
    vel = velocities(pos, demo.dt) * vmask[..., None]
    return DemoArrays(pos=pos, vel=vel, mask=mask, vmask=vmask, tactile=demo.tactile.astype(np.float64),
                      tmask=demo.tactile_mask.astype(bool), left=demo.meta.get("grasp_hand", "left") == "left",
                      dt=float(demo.dt), name=f"{demo.meta.get('task', '?')}#{demo.meta.get('demo', '?')}"
                      + (" (mirrored)" if demo.meta.get("mirrored") else ""),
                      goal=goal_bodies(pos, mask, object_groups(demo.object_names), demo.dt))


GOAL_LOOKAHEAD_S = 1.0  # what a hand comes to within the next second is what it is heading for ...
GOAL_REACH_M = 0.05  # ... if its pinch gets this close to it
UNMOVED_M = 0.005  # an object whose points all stay this close to where they were first seen lies unmoved


def goal_bodies(pos: np.ndarray, mask: np.ndarray, bodies: np.ndarray, dt: float) -> np.ndarray:
    """(T,2): per step and hand, the object body the hand acts on next: of the objects still where
    they lay at the start, the one its pinch (thumb-index midpoint) comes closest to within the next
    GOAL_LOOKAHEAD_S, if closer than GOAL_REACH_M; else -1. Assembly: the module the grasping hand
    reaches for, then the board it carries the module to (a carried object is no goal)."""
    T = len(pos)
    obj, omask = pos[:, HAND_POINTS:], mask[:, HAND_POINTS:]
    goal = np.full((T, 2), -1, int)
    n_bodies = int(bodies.max()) + 1 if len(bodies) else 0
    if not n_bodies:
        return goal
    first = np.array([obj[np.argmax(omask[:, k]), k] for k in range(obj.shape[1])])
    moved = np.maximum.accumulate(omask & (np.linalg.norm(obj - first, axis=-1) > UNMOVED_M), axis=0)
    window = max(1, round(GOAL_LOOKAHEAD_S / dt))
    for h in range(2):
        pinch = pos[:, [h * KEYPOINTS_PER_HAND + FINGERTIPS[f] for f in ("thumb", "index")]].mean(1)
        d = np.where(omask, np.linalg.norm(obj - pinch[:, None], axis=-1), np.inf)
        near = np.full((T, n_bodies), np.inf)  # closest approach over the next window, per body
        for b in range(n_bodies):
            pts = bodies == b
            db = np.where(moved[:, pts].any(1), np.inf, d[:, pts].min(1))
            padded = np.concatenate([db, np.full(window, np.inf)])
            near[:, b] = np.min([padded[k:k + T] for k in range(window + 1)], axis=0)
        best = near.argmin(1)
        goal[:, h] = np.where(near[np.arange(T), best] < GOAL_REACH_M, best, -1)
    return goal


def augmented(demos: list[Demo], mirrored: bool = True) -> list[Demo]:
    """The training set copied and mirrored (7.6.8)."""
    return list(demos) + ([mirror(d) for d in demos] if mirrored else [])


def hand_weights(left: np.ndarray, left_probability: float = 0.6) -> np.ndarray:
    """Sampling probabilities per sample so that left-grasping samples are drawn with
    ``left_probability`` in total (7.6.8); falls back to uniform when one side is absent."""
    left = np.asarray(left, bool)
    if left.all() or not left.any():
        return np.full(len(left), 1.0 / len(left))
    p = np.where(left, left_probability / left.sum(), (1.0 - left_probability) / (~left).sum())
    return p / p.sum()


@dataclass
class StepData:
    """All t -> t+1 samples of a set of demonstrations, concatenated."""

    pos: np.ndarray  # (N,P,3) at t
    vel: np.ndarray  # (N,P,3) input velocity at t
    vmask: np.ndarray  # (N,P)
    mask: np.ndarray  # (N,P)
    next_pos: np.ndarray  # (N,P,3) at t+1
    next_vel: np.ndarray  # (N,P,3) target velocity (t -> t+1)
    next_vmask: np.ndarray  # (N,P) target valid
    next_mask: np.ndarray  # (N,P)
    tactile: np.ndarray  # (N,2,R) at t
    next_tactile: np.ndarray  # (N,2,R)
    tmask: np.ndarray  # (N,2,R)
    H: np.ndarray | None  # (3,N,size) reservoir components at t
    next_H: np.ndarray | None  # (3,N,size) at t+1
    prob: np.ndarray  # (N,) sampling probabilities
    demo_index: np.ndarray  # (N,)
    step_index: np.ndarray  # (N,)
    dt: float
    window: np.ndarray | None = None  # (N,B-1,P,3) the time window's older block means (services/policy/window.py)
    wmask: np.ndarray | None = None  # (N,B-1,P) each block observed the point throughout
    goal: np.ndarray | None = None  # (N,2) goal_bodies at t

    def __len__(self) -> int:
        return len(self.pos)


def step_data(arrays: list[DemoArrays], reservoir: Reservoir | None = None, left_probability: float = 0.6,
              window: tuple[int, ...] = ()) -> StepData:
    """Flatten demonstrations into transitions; ``reservoir`` (reservoir.Reservoir) adds H (7.2.8),
    ``window`` (block lengths, ModelConfig.window) the time window's block means."""
    if not arrays:
        raise DatasetError("no demonstrations to learn from")
    dts = {round(a.dt, 9) for a in arrays}
    if len(dts) != 1:
        raise DatasetError(f"demonstrations have different time steps {sorted(dts)}; resample them first")
    for a in arrays:
        if a.steps < 3:
            raise DatasetError(f"demonstration {a.name} has {a.steps} steps; at least 3 are needed")
    cols: dict[str, list] = {k: [] for k in ("pos", "vel", "vmask", "mask", "next_pos", "next_vel", "next_vmask",
                                             "next_mask", "tactile", "next_tactile", "tmask", "H", "next_H",
                                             "left", "demo_index", "step_index", "goal")}
    for i, a in enumerate(arrays):
        cols["pos"].append(a.pos[:-1])
        cols["vel"].append(a.vel[:-1])
        cols["vmask"].append(a.vmask[:-1])
        cols["mask"].append(a.mask[:-1])
        cols["next_pos"].append(a.pos[1:])
        cols["next_vel"].append(a.vel[1:])
        cols["next_vmask"].append(a.vmask[1:])
        cols["next_mask"].append(a.mask[1:])
        cols["tactile"].append(a.tactile[:-1])
        cols["next_tactile"].append(a.tactile[1:])
        cols["tmask"].append(a.tmask[:-1] & a.tmask[1:])
        if reservoir is not None:
            comp = reservoir.components(a.vel, a.vmask)
            cols["H"].append(comp[:, :-1])
            cols["next_H"].append(comp[:, 1:])
        cols["left"].append(np.full(a.steps - 1, a.left))
        cols["demo_index"].append(np.full(a.steps - 1, i))
        cols["step_index"].append(np.arange(a.steps - 1))
        cols["goal"].append(a.goal[:-1] if a.goal is not None else np.full((a.steps - 1, 2), -1, int))
    cat = {k: np.concatenate(v, axis=1 if k in ("H", "next_H") else 0) if v else None for k, v in cols.items()}
    win, wmask = step_windows(cat["pos"], cat["mask"], cat["step_index"], window) if window else (None, None)
    return StepData(pos=cat["pos"], vel=cat["vel"], vmask=cat["vmask"], mask=cat["mask"], next_pos=cat["next_pos"],
                    next_vel=cat["next_vel"], next_vmask=cat["next_vmask"], next_mask=cat["next_mask"],
                    tactile=cat["tactile"], next_tactile=cat["next_tactile"], tmask=cat["tmask"], H=cat["H"],
                    next_H=cat["next_H"], prob=hand_weights(cat["left"], left_probability),
                    demo_index=cat["demo_index"], step_index=cat["step_index"], dt=arrays[0].dt, window=win,
                    wmask=wmask, goal=cat["goal"])


def sample_batch(data: StepData, rng: np.random.Generator, n: int, rotate: bool = True) -> dict[str, np.ndarray]:
    """n transitions drawn with the hand-swap probabilities, each rotated about gravity by its own
    random angle (7.2.4, feed-forward case); reservoir activations rotated consistently."""
    idx = rng.choice(len(data), n, p=data.prob)
    angle = rng.uniform(0.0, 2 * np.pi, n) if rotate else np.zeros(n)
    return batch_at(data, idx, angle)


def batch_at(data: StepData, idx: np.ndarray, angle: np.ndarray) -> dict[str, np.ndarray]:
    """The transitions ``idx`` rotated about gravity by ``angle`` (one per transition)."""
    a3 = angle[:, None]
    out = {"pos": rotate_z(data.pos[idx], a3), "vel": rotate_z(data.vel[idx], a3),
           "next_pos": rotate_z(data.next_pos[idx], a3), "next_vel": rotate_z(data.next_vel[idx], a3),
           "vmask": data.vmask[idx], "mask": data.mask[idx], "next_vmask": data.next_vmask[idx],
           "next_mask": data.next_mask[idx], "tactile": data.tactile[idx], "next_tactile": data.next_tactile[idx],
           "tmask": data.tmask[idx], "angle": angle, "index": idx, "phase": data.step_index[idx] * data.dt}
    if data.goal is not None:
        out["goal"] = data.goal[idx]
    if data.window is not None:
        out["window"] = rotate_z(data.window[idx], angle[:, None, None])
        out["wmask"] = data.wmask[idx]
    if data.H is not None:
        out["H"] = Reservoir.rotated(data.H[:, idx], angle)
        out["next_H"] = Reservoir.rotated(data.next_H[:, idx], angle)
    return out


# --- recordings --------------------------------------------------------------------------------
def demos_from_mcap(path: str | Path | list[str | Path], dt: float = 0.02, max_gap_s: float = 0.5, min_steps: int = 20,
                    report: list[str] | None = None, window_s: tuple[float, float | None] | None = None
                    ) -> list[Demo]:
    """Demonstrations of one MCAP recording (scene + session keys), resampled onto ``dt``. A segmented
    recording reads as one: ``path`` may be its first segment, a directory or a list of segments.
    ``window_s`` (start, end or None), seconds from the recording's first message: only the scenes
    logged within it are used (a trim; the session labels before it still name the demonstration).

    NaN keypoints are masked, a gap longer than ``max_gap_s`` ends a demonstration, demonstrations
    shorter than ``min_steps`` are dropped; each such event is appended to ``report`` with the
    demonstration and the time. Raises DatasetError when nothing usable is in the file."""
    files = recording_segments(path)
    path = Path(path) if isinstance(path, (str, Path)) else files[0] if files else Path("recording")
    if not files or not all(f.exists() for f in files):
        raise DatasetError(f"{path}: no such recording")
    report = report if report is not None else []
    scenes, sessions = [], []
    try:
        with AnyReader(files, default_typestore=msgs.typestore()) as reader:
            topics = {c.topic for c in reader.connections}
            missing = [k for k in (SCENE_KEY, SESSION_KEY) if k not in topics]
            if missing:
                raise DatasetError(f"{path}: no messages on {', '.join(missing)}; record while the world and "
                                   f"recon services run")
            conns = [c for c in reader.connections if c.topic in (SCENE_KEY, SESSION_KEY)]
            lo, hi = _log_window(reader.start_time, window_s)
            for conn, log_time, raw in reader.messages(connections=conns):
                if conn.topic == SCENE_KEY and not lo <= log_time <= hi:
                    continue
                msg = reader.deserialize(raw, conn.msgtype)
                (scenes if conn.topic == SCENE_KEY else sessions).append((msgs.stamp_seconds(msg.header.stamp), msg))
    except DatasetError:
        raise
    except Exception as exc:  # rosbags raises several unrelated types for damaged files
        raise DatasetError(f"{path}: unreadable recording ({type(exc).__name__}: {exc})") from exc
    return demos_from_messages(scenes, sessions, dt, max_gap_s, min_steps, report, str(path))


def _log_window(start_ns: int, window_s: tuple[float, float | None] | None) -> tuple[int, float]:
    """Log-time bounds (ns) of a trim window given in seconds from the first message."""
    if window_s is None:
        return 0, np.inf
    lo, hi = window_s
    return start_ns + int(round(lo * 1e9)), np.inf if hi is None else start_ns + int(round(hi * 1e9))


def demos_from_messages(scenes: list, sessions: list, dt: float = 0.02, max_gap_s: float = 0.5,
                        min_steps: int = 20, report: list[str] | None = None, source: str = "recording"
                        ) -> list[Demo]:
    """Pure part of ``demos_from_mcap``: (stamp seconds, Scene) and (stamp seconds, Session) pairs in the
    order they were logged. A stamp that steps back by more than ``CLOCK_RESTART_S`` is a world
    restart (its clock starts again at 0): labels and scenes after it form a new epoch, so a
    demonstration index that repeats after a restart is another demonstration, never merged."""
    report = report if report is not None else []
    if not scenes:
        raise DatasetError(f"{source}: no scene messages")
    if not sessions:
        raise DatasetError(f"{source}: no session messages, so no demonstration labels")
    scene_epochs, session_epochs = clock_epochs(scenes), clock_epochs(sessions)
    if len(scene_epochs) != len(session_epochs):
        report.append(f"{source}: the clock restarted {len(session_epochs) - 1} times in the labels but "
                      f"{len(scene_epochs) - 1} times in the scenes; epochs are paired in order")
    groups: dict[tuple[int, int], list] = {}
    unlabeled = 0
    for epoch, (scene_part, session_part) in enumerate(zip(scene_epochs, session_epochs, strict=False)):
        labels = sorted(session_part, key=lambda s: s[0])
        stamps = np.array([s[0] for s in labels])
        for t, scene in sorted(scene_part, key=lambda s: s[0]):
            k = int(np.searchsorted(stamps, t, side="right")) - 1
            if k < 0:
                unlabeled += 1
                continue
            groups.setdefault((epoch, int(labels[k][1].demo)), []).append((t, scene, labels[k][1]))
    unlabeled += sum(len(part) for part in scene_epochs[len(session_epochs):])
    if unlabeled:
        report.append(f"{source}: {unlabeled} scenes before the first session label ignored")
    demos = []
    for (epoch, index), items in sorted(groups.items()):
        try:
            demo = _one_demo(source, index, items, dt, max_gap_s, report, epoch)
        except DatasetError as exc:
            report.append(str(exc))
            continue
        if demo.steps < min_steps:
            report.append(f"{source}: demonstration {index} dropped: {demo.steps} steps < {min_steps}")
            continue
        demos.append(demo)
    if not demos:
        raise DatasetError(f"{source}: no usable demonstration ({'; '.join(report) or 'none labelled'})")
    return demos


CLOCK_RESTART_S = 0.25  # a stamp this far behind the newest one: the clock started again


def clock_epochs(stamped: list) -> list[list]:
    """``(stamp, message)`` pairs in log order, cut where the stamp steps back by more than
    CLOCK_RESTART_S (a world restart); small reorderings between publishers stay in one epoch."""
    epochs: list[list] = [[]]
    newest = -np.inf
    for item in stamped:
        if item[0] < newest - CLOCK_RESTART_S:
            epochs.append([])
            newest = -np.inf
        newest = max(newest, item[0])
        epochs[-1].append(item)
    return epochs


def _one_demo(source: str, index: int, items: list, dt: float, max_gap_s: float, report: list[str],
              epoch: int = 0) -> Demo:
    times = np.array([t for t, _, _ in items])
    if len(times) > 1:
        gaps = np.flatnonzero(np.diff(times) > max_gap_s)
        if len(gaps):
            g = gaps[0]
            report.append(f"{source}: demonstration {index}: gap of {times[g + 1] - times[g]:.2f} s at "
                          f"t={times[g] - times[0]:.2f} s; kept the part before it")
            items, times = items[:g + 1], times[:g + 1]
    first = items[0][1]
    names = list(first.object_names)
    n_obj = len(names)
    regions = len(TACTILE_REGIONS)
    rows = []
    for t, s, _ in items:
        try:
            hands = np.asarray(s.hand_keypoints, float).reshape(len(HAND_NAMES), KEYPOINTS_PER_HAND, 3)
            hmask = np.asarray(s.hand_mask, bool).reshape(len(HAND_NAMES), KEYPOINTS_PER_HAND)
            if list(s.object_names) != names:
                raise ValueError(f"object names changed to {list(s.object_names)}")
            objs = np.asarray(s.object_keypoints, float).reshape(n_obj, 3)
            omask = np.asarray(s.object_mask, bool).reshape(n_obj)
            tact = (np.asarray(s.tactile, float).reshape(2, regions) if len(s.tactile) else np.zeros((2, regions)))
            tmask = (np.asarray(s.tactile_mask, bool).reshape(2, regions) if len(s.tactile_mask)
                     else np.zeros((2, regions), bool))
        except ValueError as exc:
            raise DatasetError(f"{source}: demonstration {index} rejected: malformed scene at "
                               f"t={t - times[0]:.2f} s ({exc})") from exc
        rows.append((hands, hmask, objs, omask, tact, tmask))
    hands, hmask, objs, omask, tact, tmask = (np.array(c) for c in zip(*rows, strict=True))
    bad_h, bad_o = ~np.isfinite(hands).all(-1), ~np.isfinite(objs).all(-1)
    bad_t = ~np.isfinite(tact)
    if bad_h.any() or bad_o.any() or bad_t.any():
        first_bad = np.flatnonzero(bad_h.any(axis=(1, 2)) | bad_o.any(axis=1) | bad_t.any(axis=(1, 2)))[0]
        report.append(f"{source}: demonstration {index}: NaN keypoints or tactile from t="
                      f"{times[first_bad] - times[0]:.2f} s masked ({int(bad_h.sum() + bad_o.sum())} keypoints)")
    hmask &= ~bad_h
    omask &= ~bad_o
    tmask &= ~bad_t
    grid = np.arange(times[0], times[-1] + 1e-9, dt)
    idx = np.clip(np.searchsorted(times, grid, side="right") - 1, 0, len(times) - 1)  # latest sample at or before

    def pick(x: np.ndarray) -> np.ndarray:
        return np.nan_to_num(x[idx])

    label = items[-1][2]
    phases = [items[i][2].phase for i in idx]
    return Demo(dt=dt, hands=pick(hands).astype(np.float32), hand_mask=pick(hmask).astype(np.uint8),
                object_names=names, objects=pick(objs).astype(np.float32), object_mask=pick(omask).astype(np.uint8),
                tactile=pick(tact).astype(np.float32), tactile_mask=pick(tmask).astype(np.uint8), phase=phases,
                meta={"task": label.task, "demo": index, "tactile_hand": label.tactile_hand,
                      "grasp_hand": _grasp_hand(pick(hands), pick(objs)), "source": source,
                      "epoch": epoch, "start_s": float(times[0])})


def _grasp_hand(hands: np.ndarray, objects: np.ndarray) -> str:
    """The hand whose pinch point comes closest to any object point (the session does not say)."""
    pinch = 0.5 * (hands[:, :, 4] + hands[:, :, 8])  # (T,2,3)
    d = np.linalg.norm(pinch[:, :, None] - objects[:, None], axis=-1).min(axis=(0, 2))
    return HAND_NAMES[int(np.argmin(d))]
