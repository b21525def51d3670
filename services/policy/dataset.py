"""Demonstrations from MCAP recordings: scene + session labels -> Demo objects (pure of Zenoh).

Scenes are split into demonstrations by the session's demo index and resampled onto a fixed
step. Missing keys, gaps and NaN keypoints are handled explicitly: NaN keypoints become masked,
a gap longer than ``max_gap_s`` ends the demonstration (reported), a recording without scene or
session messages is rejected with a message naming what is missing.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from shared import msgs
from shared.demo import Demo

SCENE = "xm/recon/main/scene"
SESSION = "xm/world/sim/session"


class DatasetError(ValueError):
    """A recording that cannot give demonstrations; the message says which and why."""


def demos_from_mcap(path: str | Path, dt: float = 0.02, max_gap_s: float = 0.5,
                    min_steps: int = 20) -> tuple[list[Demo], list[str]]:
    """Returns the demonstrations and a list of warnings (gaps, NaN masked, short demos dropped)."""
    from rosbags.highlevel import AnyReader

    path = Path(path)
    scenes, sessions = [], []
    with AnyReader([path], default_typestore=msgs.typestore()) as reader:
        topics = {c.topic for c in reader.connections}
        missing = [k for k in (SCENE, SESSION) if k not in topics]
        if missing:
            raise DatasetError(f"{path}: no messages on {missing}; record with `xm record` while the world "
                               f"and recon run")
        conns = [c for c in reader.connections if c.topic in (SCENE, SESSION)]
        for conn, _, raw in reader.messages(connections=conns):
            msg = reader.deserialize(raw, conn.msgtype)
            (scenes if conn.topic == SCENE else sessions).append((msgs.stamp_seconds(msg.header.stamp), msg))
    sessions.sort(key=lambda s: s[0])
    warnings: list[str] = []
    groups: dict[int, list] = {}
    for t, scene in sorted(scenes, key=lambda s: s[0]):
        label = [s for ts, s in sessions if ts <= t]
        if not label:
            continue
        groups.setdefault(int(label[-1].demo), []).append((t, scene, label[-1]))
    demos = []
    for index, items in groups.items():
        demo = _demo(path, index, items, dt, max_gap_s, warnings)
        if demo is None or demo.steps < min_steps:
            warnings.append(f"{path}: demonstration {index} dropped (fewer than {min_steps} steps)")
            continue
        demos.append(demo)
    return demos, warnings


def _demo(path: Path, index: int, items: list, dt: float, max_gap_s: float, warnings: list[str]) -> Demo | None:
    times = np.array([t for t, _, _ in items])
    gaps = np.flatnonzero(np.diff(times) > max_gap_s)
    if len(gaps):
        cut = gaps[0] + 1
        warnings.append(f"{path}: demonstration {index}: gap of {np.diff(times)[gaps[0]]:.2f} s at "
                        f"t={times[gaps[0]]:.2f} s; kept the part before it")
        items, times = items[:cut], times[:cut]
    first = items[0][1]
    n_obj = len(first.object_names)
    hands = np.array([np.asarray(s.hand_keypoints, float).reshape(2, 21, 3) for _, s, _ in items])
    hmask = np.array([np.asarray(s.hand_mask).reshape(2, 21) for _, s, _ in items]).astype(bool)
    objs = np.array([np.asarray(s.object_keypoints, float).reshape(n_obj, 3) for _, s, _ in items])
    omask = np.array([np.asarray(s.object_mask) for _, s, _ in items]).astype(bool)
    tact = np.array([np.asarray(s.tactile, float).reshape(2, -1) if len(s.tactile) else np.zeros((2, 6))
                     for _, s, _ in items])
    tmask = np.array([np.asarray(s.tactile_mask).reshape(2, -1) if len(s.tactile_mask) else np.zeros((2, 6))
                      for _, s, _ in items]).astype(bool)
    nan_h, nan_o = ~np.isfinite(hands).all(-1), ~np.isfinite(objs).all(-1)
    if nan_h.any() or nan_o.any():
        first_bad = times[np.flatnonzero(nan_h.any(axis=(1, 2)) | nan_o.any(axis=1))[0]]
        warnings.append(f"{path}: demonstration {index}: NaN keypoints from t={first_bad:.2f} s masked")
    hmask &= ~nan_h
    omask &= ~nan_o
    grid = np.arange(times[0], times[-1], dt)

    def resample(x: np.ndarray) -> np.ndarray:
        idx = np.clip(np.searchsorted(times, grid), 0, len(times) - 1)
        return np.nan_to_num(x[idx])

    label = items[-1][2]
    return Demo(dt=dt, hands=resample(hands).astype(np.float32), hand_mask=resample(hmask).astype(np.uint8),
                object_names=list(first.object_names), objects=resample(objs).astype(np.float32),
                object_mask=resample(omask).astype(np.uint8), tactile=resample(tact).astype(np.float32),
                tactile_mask=resample(tmask).astype(np.uint8), phase=[label.phase] * len(grid),
                meta={"task": label.task, "demo": index, "tactile_hand": label.tactile_hand,
                      "grasp_hand": label.tactile_hand, "source": str(path)})
