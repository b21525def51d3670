"""recon's bench from rendered images (bench/recon.py): held-out sessions rendered as camhub reads
them, the learned detector on the JPEG windows, recon's stages live, offline, and aniposelib on the
same 2-D detections. Errors against the simulator's truth (evaluation only)."""

from __future__ import annotations

import json
import os
import subprocess
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from perception.occlusion import OBJECT_CLEARANCE_M, hidden_by_capsules, hidden_by_geoms
from services.camhub.camera_info import encode_jpeg
from services.camhub.roi import CameraGeometry, RoiParams, missing_hand, rig_windows, tracked_points
from services.recon.cli import Frames, refine_hands
from services.recon.detector import HAND_PRESENT_CONFIDENCE, CameraModel, SimulatedDetector, View
from services.recon.hand_model import CHAINS
from services.recon.objects import task_keypoint_names
from services.recon.offline import OfflineConfig
from services.recon.pipeline import Reconstruction, Reconstructor
from services.recon.service import decode_window
from services.recon.triangulation import project
from services.world.appearance import session_look, teacher_capsules
from services.world.render import SceneRenderer, snapshot
from services.world.sim import WorldSim
from shared.demo import HAND_NAMES, KEYPOINTS_PER_HAND
from shared.geometry import projection

ROOT = Path(__file__).resolve().parents[1]
ANIPOSE_PYTHON = ROOT / ".cache" / "anipose-venv" / "bin" / "python"
TASK = "assembly"  # the held-out sessions' task (the shipped network's objects)
THRESHOLD = 0.3  # confidence below which a 2-D detection counts as none (xm detector eval's)
ERROR_KEYS = ("hand", "obj", "obj_k", "obj_near", "near_all", "cover_h", "cover_o")  # what errors() returns
NEAR_BANDS = ((0.0, 0.03), (0.03, 0.06), (0.06, np.inf))  # object keypoint to nearest hand keypoint (m)
BONES = [(0, int(c[0])) for c in CHAINS] + [(int(a), int(b)) for c in CHAINS
                                             for a, b in zip(c[:-1], c[1:], strict=True)]


@dataclass
class Session:
    """One held-out session: per frame set the truth (N,3), whether each point exists (hands parked
    off the cell do not), the 2-D detections of both detectors and what recon made of them live."""
    seed: int
    truth: list = field(default_factory=list)
    present: list = field(default_factory=list)
    uv: list = field(default_factory=list)  # learned (C,N,2)
    conf: list = field(default_factory=list)
    live: list = field(default_factory=list)  # Reconstruction, learned
    sim_live: list = field(default_factory=list)  # Reconstruction, simulated detector on the same windows
    sim_uv: list = field(default_factory=list)
    sim_seen: list = field(default_factory=list)
    rois: list = field(default_factory=list)  # (C,4) readout windows
    hidden: list = field(default_factory=list)  # (C,K) object keypoints occluded per view (occlusion=True)


def ray_deviation(P: np.ndarray, points: np.ndarray, uv: np.ndarray, used: np.ndarray) -> list[float]:
    """Per used (view, point): the distance (m) from the triangulated point to the view's ray
    through its detection."""
    out = []
    for c in range(len(P)):
        M, p4 = P[c][:, :3], P[c][:, 3]
        centre = -np.linalg.solve(M, p4)
        idx = np.flatnonzero(used[c])
        if not len(idx):
            continue
        d = np.linalg.solve(M, np.c_[uv[c, idx], np.ones(len(idx))].T).T
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        out += list(np.linalg.norm(np.cross(points[idx] - centre, d), axis=1))
    return out


def run_sessions(detector: object, seeds: list[int], task: str, frames: int, rate_hz: float, width: int,
                 height: int, times: dict, occlusion: bool = False) -> list[Session]:
    """Renders each session's frame sets with camhub's windows (around recon's last scene, full
    frames every tenth trigger), encodes them as camhub does, then decodes, detects and
    reconstructs them as recon does; stage times go into ``times``. ``occlusion``: also record which
    object keypoints each view's line of sight finds hidden (perception/occlusion.py)."""
    renderer = SceneRenderer(task, width, height)
    geoms = [CameraGeometry(c.name, width, height, c.K, np.zeros(5), c.world_T_cam) for c in renderer.cameras]
    P = np.stack([projection(c.K, c.world_T_cam) for c in renderer.cameras])
    params = RoiParams()
    out = []
    try:
        for seed in seeds:
            if hasattr(detector, "reset"):
                detector.reset()  # a new session: no object's detections carry over
            sim = WorldSim(task, seed=seed)
            steps = int(round(1.0 / rate_hz / sim.physics_dt))
            rec = Reconstructor(task, hand_present_confidence=getattr(detector, "hand_present_confidence", 0.0))
            rec_sim = Reconstructor(task)
            simulated = SimulatedDetector(1.0, 0.08, seed=seed)
            s, last = Session(seed), None
            for trigger in range(frames):
                sim.step(steps)
                hands = sim.hand_keypoints()
                _, objects = sim.object_keypoints()
                hv, ov = sim.visibility()
                truth = np.concatenate([hands.reshape(-1, 3), objects])
                present = np.r_[np.repeat(~np.all(hands[..., 2] < -0.5, axis=1), hands.shape[1]),
                                np.ones(len(objects), bool)]
                points = None if last is None else tracked_points(last.hands, last.hand_mask)
                lost = last is not None and missing_hand(last.hand_mask, len(last.hand_mask))
                windows, _ = rig_windows(geoms, points, 1.0 / rate_hz, trigger, params, lost)
                rois = [tuple(windows[g.name]) for g in geoms]
                snap = snapshot(sim.task, sim.data, sim.robot_name, seed, sim.demo, sim.teacher.tactile_hand)
                blobs = [encode_jpeg(img, 80) for img in renderer.render(snap, rois)]
                models = [CameraModel(P[i], width, height, rois[i]) for i in range(len(geoms))]
                t0 = time.perf_counter()
                views = [View(g.name, m, decode_window(b, m)) for g, m, b in zip(geoms, models, blobs, strict=True)]
                t1, c1 = time.perf_counter(), time.process_time()
                uv, conf = detector.detect(views)
                t2 = time.perf_counter()
                times["cpu_detect"].append(time.process_time() - c1)
                for k, v in getattr(detector, "times", {}).items():  # the detector's own stages
                    times.setdefault(f"detect_{k}", []).append(v)
                c0 = time.process_time()
                r = rec.step(P, uv, conf, np.array(rois, float))
                times["cpu_reconstruct"].append(time.process_time() - c0)
                times["decode"].append(t1 - t0)
                times["detect"].append(t2 - t1)
                for k in ("triangulate", "fit_hands", "fit_objects"):
                    times[k].append(r.times[k])
                sim_uv, seen = simulated.detect(models, truth, np.r_[hv.ravel(), ov].astype(bool))
                s.sim_live.append(rec_sim.step(P, sim_uv, seen.astype(float)))
                s.sim_uv.append(sim_uv)
                s.sim_seen.append(seen)
                s.truth.append(truth)
                s.present.append(present)
                s.uv.append(uv)
                s.conf.append(conf)
                s.live.append(r)
                s.rois.append(np.array(rois, float))
                if occlusion:
                    capsules = teacher_capsules(hands, HAND_NAMES, snap.glove_hand, session_look(seed, snap.demo))
                    s.hidden.append(_objects_hidden(renderer, P, objects, capsules))
                last = r
            out.append(s)
    finally:
        renderer.close()
    return out


def _objects_hidden(renderer: SceneRenderer, P: np.ndarray, objects: np.ndarray, capsules: list) -> np.ndarray:
    """(C,K) object keypoints whose line of sight from each camera passes through a hand or hits a
    geom short of them (the renderer's data holds the frame set just drawn)."""
    m = renderer.model
    skip = {m.body(f"{h}_kp{k}").id for h in HAND_NAMES for k in range(KEYPOINTS_PER_HAND)}
    clearance = np.full(len(objects), OBJECT_CLEARANCE_M)
    out = []
    for c in range(len(P)):
        eye = -np.linalg.solve(P[c][:, :3], P[c][:, 3])
        out.append(hidden_by_capsules(eye, objects, clearance, capsules)
                   | hidden_by_geoms(m, renderer.data, eye, objects, clearance, skip))
    return np.array(out)


def first_frames(s: Session, n: int) -> Session:
    """The session's first ``n`` frame sets."""
    return Session(s.seed, s.truth[:n], s.present[:n], s.uv[:n], s.conf[:n], s.live[:n], s.sim_live[:n],
                   s.sim_uv[:n], s.sim_seen[:n], s.rois[:n], s.hidden[:n])


def errors(recs: list[Reconstruction], s: Session) -> dict:
    """Per keypoint errors (m) of what recon reported, and the shares reported."""
    hand, obj, obj_k, obj_near, cover_h, cover_o, near_all = [], [], [], [], [], [], []
    for r, truth, present in zip(recs, s.truth, s.present, strict=True):
        nh = r.hands.size // 3
        hm = r.hand_mask.ravel().astype(bool) & present[:nh]
        om = r.object_mask.astype(bool)
        near = hand_distance(truth[nh:], truth[:nh][present[:nh]])
        hand += list(np.linalg.norm(r.hands.reshape(-1, 3) - truth[:nh], axis=1)[hm])
        obj += list(np.linalg.norm(r.objects - truth[nh:], axis=1)[om])
        obj_k += list(np.flatnonzero(om))
        obj_near += list(near[om])
        near_all += list(near)
        cover_h.append(hm.sum() / max(present[:nh].sum(), 1))
        cover_o.append(om.mean())
    return {"hand": hand, "obj": obj, "obj_k": obj_k, "obj_near": obj_near, "near_all": near_all,
            "cover_h": cover_h, "cover_o": cover_o}


def hand_distance(objects: np.ndarray, hands: np.ndarray) -> np.ndarray:
    """Per true object keypoint (K,3): the distance (m) to the nearest true keypoint of a hand in
    the cell (inf without one)."""
    if not len(hands):
        return np.full(len(objects), np.inf)
    return np.linalg.norm(objects[:, None] - hands[None], axis=-1).min(axis=1)


def by_hand_distance(err: dict) -> dict | None:
    """The object error split by how far the nearest hand is from the true keypoint: per band its
    reported keypoints, their mean / median error, their share of the error sum, and the share of
    the band's keypoints reported."""
    if not err.get("obj"):
        return None
    e, d, d_all = np.asarray(err["obj"]), np.asarray(err["obj_near"]), np.asarray(err["near_all"])
    out = {}
    for lo, hi in NEAR_BANDS:
        sel, sel_all = (d >= lo) & (d < hi), (d_all >= lo) & (d_all < hi)
        name = f"{100 * lo:.0f}-{100 * hi:.0f} cm" if np.isfinite(hi) else f">= {100 * lo:.0f} cm"
        out[name] = {"reported": int(sel.sum()), "mean_mm": mm(e[sel]),
                     "median_mm": round(1000 * float(np.median(e[sel])), 2) if sel.any() else None,
                     "share_of_error_sum": round(float(e[sel].sum() / e.sum()), 3),
                     "coverage": round(float(sel.sum() / max(sel_all.sum(), 1)), 3)}
    return out


def geometry(recs: list[Reconstruction], uvs: list, P: np.ndarray) -> tuple[list, list]:
    """Reprojection error (px) of the triangulated points in their inlier views, and the ray
    deviation (m): the distance from each triangulated point to its inlier views' rays."""
    reproj, rays = [], []
    for r, uv in zip(recs, uvs, strict=True):
        used = r.inliers.astype(bool)
        pix, _ = project(P, r.triangulated)
        reproj += list(np.linalg.norm(pix - uv, axis=-1)[used])
        rays += ray_deviation(P, r.triangulated, uv, used)
    return reproj, rays


def offline(s: Session, P: np.ndarray, task: str, rate_hz: float) -> tuple[list[Reconstruction], float]:
    """``xm recon``'s offline stages (two passes, then each hand's trajectory refined) on the
    session's learned detections; per frame set hands/objects as Reconstructions."""
    cams = {f"cam{i}": CameraModel(P[i], 0, 0) for i in range(len(P))}
    frames = Frames(cameras=cams, stamps=[i / rate_hz for i in range(len(s.uv))], uv=list(s.uv),
                    confidence=list(s.conf), hand_present_confidence=HAND_PRESENT_CONFIDENCE)
    t0 = time.perf_counter()
    result = refine_hands(frames, task, OfflineConfig())
    seconds = time.perf_counter() - t0
    return [Reconstruction(h, m, live.hand_fitted, r.objects, r.object_mask, live.object_posed, live.inliers,
                           live.triangulated)
            for h, m, r, live in zip(result.hands, result.hand_mask, result.live, s.live, strict=True)], seconds


def anipose(sessions: list[Session], P: np.ndarray, width: int, height: int,
            python: Path = ANIPOSE_PYTHON) -> dict | str:
    """aniposelib's RANSAC triangulation and its optimisation on the learned detections (hands);
    per session (T,42,3) arrays, or why it did not run."""
    if not python.exists():
        return f"no aniposelib venv at {python.parent.parent} (bench/calibration.py makes it)"
    K, rvec, tvec = [], [], []
    for p in P:
        k, r, t = cv2.decomposeProjectionMatrix(p)[:3]
        k = k / k[2, 2]
        K.append(k)
        rvec.append(cv2.Rodrigues(r)[0].ravel())
        tvec.append((-r @ (t[:3] / t[3])).ravel())
    nh = 2 * KEYPOINTS_PER_HAND
    data = {"K": np.array(K), "rvec": np.array(rvec), "tvec": np.array(tvec),
            "size": np.array([[width, height]] * len(P)), "sessions": len(sessions),
            "bones": np.array(BONES + [(a + KEYPOINTS_PER_HAND, b + KEYPOINTS_PER_HAND) for a, b in BONES])}
    for i, s in enumerate(sessions):
        uv = np.stack(s.uv)[:, :, :nh].transpose(1, 0, 2, 3).copy()  # (C,T,J,2)
        conf = np.stack(s.conf)[:, :, :nh].transpose(1, 0, 2)
        uv[conf < THRESHOLD] = np.nan
        data[f"uv_{i}"], data[f"score_{i}"] = uv, conf
    with tempfile.TemporaryDirectory() as tmp:
        src, dst = Path(tmp) / "in.npz", Path(tmp) / "out.npz"
        np.savez(src, **data)
        env = {**os.environ, "OMP_NUM_THREADS": "2", "NUMBA_NUM_THREADS": "2"}
        proc = subprocess.run([str(python), str(ROOT / "bench" / "anipose" / "triangulate_sessions.py"),
                               str(src), str(dst)], capture_output=True, text=True, env=env)
        if proc.returncode != 0:
            return f"aniposelib failed: {proc.stderr[-2000:]}"
        res = np.load(dst)
        return {k: res[k] for k in res.files}


def point_errors(points: np.ndarray, s: Session) -> tuple[list, float]:
    """Errors (m) of (T,42,3) hand points against truth where finite and the hand present; coverage."""
    truth = np.stack(s.truth)[:, :points.shape[1]]
    present = np.stack(s.present)[:, :points.shape[1]]
    ok = np.all(np.isfinite(points), axis=-1) & present
    return list(np.linalg.norm(points - truth, axis=-1)[ok]), float(ok.sum() / max(present.sum(), 1))


def mm(values: list) -> float | None:
    return round(1000 * float(np.mean(values)), 2) if len(values) else None


def per_keypoint(err: dict) -> dict | None:
    """Mean error (mm) per object keypoint, named as the task names them."""
    if not err.get("obj_k"):
        return None
    k, e = np.asarray(err["obj_k"]), np.asarray(err["obj"])
    names = task_keypoint_names(TASK)
    return {names[i]: round(1000 * float(e[k == i].mean()), 2) for i in np.unique(k)}


def summary(err: dict, reproj: list, rays: list) -> dict:
    return {"hand_mean_error_mm": mm(err["hand"]),
            "hand_median_error_mm": round(1000 * float(np.median(err["hand"])), 2) if err["hand"] else None,
            "hand_p95_error_mm": round(1000 * float(np.percentile(err["hand"], 95)), 2) if err["hand"] else None,
            "object_mean_error_mm": mm(err["obj"]),
            "object_median_error_mm": round(1000 * float(np.median(err["obj"])), 2) if err["obj"] else None,
            "object_mean_error_mm_per_keypoint": per_keypoint(err),
            "object_error_by_hand_distance": by_hand_distance(err),
            "reprojection_px": round(float(np.mean(reproj)), 2) if reproj else None,
            "ray_deviation_mm": mm(rays),
            "coverage": {"hands": round(float(np.mean(err["cover_h"])), 3),
                         "objects": round(float(np.mean(err["cover_o"])), 3)}}


def load_average() -> list[float]:
    return [round(v, 2) for v in os.getloadavg()]


def dump(row: dict) -> str:
    return json.dumps(row, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o))
