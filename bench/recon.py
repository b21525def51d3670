"""3-D reconstruction on held-out simulated sessions: accuracy against truth and time per stage.

From images (``images`` in the JSON; bench/_recon_images.py): held-out assembly sessions
rendered at the live rig's 256x192 through camhub's readout windows (around recon's last scene,
full frames every tenth trigger) and JPEG quality, the shipped learned detector on the decoded
windows, recon's stages live and ``xm recon``'s offline refinement, against truth; beside them the
simulated detector (projected truth, 1 px noise, 8 % dropouts, occlusion) on the same windows, and
aniposelib (RANSAC triangulation; its optimisation with temporal smoothing and bone-length
constraints) on the same learned 2-D detections. P6 time: decode + detect + triangulate + fit of
each 7-camera frame set, medians.

From projected truth (``rows``): WorldSim teacher demonstrations with seeds no other bench or test uses, sampled at the
live deployment's 5 Hz. 2-D detections: the simulated detector (truth projected into the 7
cameras, pixel noise, random dropouts, the world's occlusion estimate, a few % outliers anywhere
in the image). The same detections go through recon's pipeline (robust triangulation, articulated
hand fit, rigid objects) and through plain DLT triangulation (the baseline); errors are measured
against truth on the keypoints each method reports (masked ones left out; their share is the
coverage). Timing: medians per 7-camera frame set of decoding the JPEG windows (one rendered frame
set, encoded as camhub does), the simulated detector (a stand-in: the learned detector's time is
measured by its own bench), triangulation and the fits. Wall time on a shared machine measures the
neighbours too. Writes .bench/recon.json.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # runnable as a script from anywhere
sys.path.insert(0, str(Path(__file__).resolve().parent))  # its helper module

import _recon_images as images  # noqa: E402
import _recon_live  # noqa: E402

from services.camhub.camera_info import encode_jpeg  # noqa: E402
from services.recon.detector import CameraModel, SimulatedDetector  # noqa: E402
from services.recon.onnx_graphs import PRECISIONS  # noqa: E402
from services.recon.pipeline import Reconstructor  # noqa: E402
from services.recon.service import decode_window  # noqa: E402
from services.recon.triangulation import project, triangulate  # noqa: E402
from services.world.model import camera_specs  # noqa: E402
from services.world.sim import WorldSim  # noqa: E402
from shared.geometry import projection  # noqa: E402

SESSIONS = ((7301, "assembly"), (7302, "pick_place"), (7303, "assembly"), (7304, "pick_place"))
SIZES = ((256, 192), (640, 480))
IMAGE_SESSIONS = (7301, 7303, 7305, 7307)  # assembly: the shipped network's objects


def session_frames(seed: int, task: str, frames: int, rate_hz: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """(truth points (N,3) hands first, visible (N,)) per frame set."""
    sim = WorldSim(task, seed=seed)
    steps = int(round(1.0 / rate_hz / sim.physics_dt))
    out = []
    for _ in range(frames):
        sim.step(steps)
        _, objects = sim.object_keypoints()
        hands_visible, objects_visible = sim.visibility()
        out.append((np.concatenate([sim.hand_keypoints().reshape(-1, 3), objects]),
                    np.concatenate([hands_visible.ravel(), objects_visible]).astype(bool)))
    return out


def reprojection(P: np.ndarray, points: np.ndarray, uv: np.ndarray, used: np.ndarray) -> list[float]:
    pix, _ = project(P, points)
    return list(np.linalg.norm(pix - uv, axis=-1)[used])


def run(width: int, height: int, args: argparse.Namespace) -> dict:
    acc = {k: [] for k in ("hand", "hand_dlt", "hand_tri", "obj", "obj_dlt", "reproj", "reproj_dlt")}
    cover = {k: [] for k in ("hand", "hand_dlt", "obj", "obj_dlt")}
    times = {k: [] for k in ("detect", "triangulate", "fit_hands", "fit_objects")}
    fitted, cpu = [], []
    for seed, task in SESSIONS[:args.sessions]:
        cams = [CameraModel(projection(c.K, c.world_T_cam), width, height) for c in camera_specs(width, height)]
        P = np.stack([c.P for c in cams])
        det = SimulatedDetector(args.noise, args.dropout, seed=seed, outliers=args.outliers)
        rec = Reconstructor(task)
        tri_only = Reconstructor(task, fit_hands=False)
        for truth, visible in session_frames(seed, task, args.frames, args.rate):
            t0 = time.perf_counter()
            uv, seen = det.detect(cams, truth, visible)
            times["detect"].append(time.perf_counter() - t0)
            c0 = time.process_time()
            r = rec.step(P, uv, seen.astype(float))
            cpu.append(time.process_time() - c0)
            for k in ("triangulate", "fit_hands", "fit_objects"):
                times[k].append(r.times[k])
            base, bmask = triangulate(P, uv, seen)
            tri = tri_only.step(P, uv, seen.astype(float))
            nh = r.hands.size // 3
            present = np.abs(truth[:nh]).sum(axis=1) > 0  # robot mode puts the hands away: nothing to grade
            hm, bm = r.hand_mask.ravel().astype(bool) & present, bmask[:nh].astype(bool) & present
            acc["hand"] += list(np.linalg.norm(r.hands.reshape(-1, 3) - truth[:nh], axis=1)[hm])
            acc["hand_dlt"] += list(np.linalg.norm(base[:nh] - truth[:nh], axis=1)[bm])
            tm = tri.hand_mask.ravel().astype(bool) & present
            acc["hand_tri"] += list(np.linalg.norm(tri.hands.reshape(-1, 3) - truth[:nh], axis=1)[tm])
            om, obm = r.object_mask.astype(bool), bmask[nh:].astype(bool)
            acc["obj"] += list(np.linalg.norm(r.objects - truth[nh:], axis=1)[om])
            acc["obj_dlt"] += list(np.linalg.norm(base[nh:] - truth[nh:], axis=1)[obm])
            cover["hand"].append(hm.sum() / max(present.sum(), 1))
            cover["hand_dlt"].append(bm.sum() / max(present.sum(), 1))
            cover["obj"].append(om.mean())
            cover["obj_dlt"].append(obm.mean())
            fitted.append(r.hand_fitted.mean())
            ours = np.concatenate([r.hands.reshape(-1, 3), r.objects])
            acc["reproj"] += reprojection(P, ours, uv, r.inliers & np.concatenate([hm, om])[None])
            acc["reproj_dlt"] += reprojection(P, np.nan_to_num(base), uv, seen & bmask.astype(bool)[None])
    mm = {k: round(1000 * float(np.mean(v)), 2) for k, v in acc.items() if not k.startswith("reproj")}
    return {
        "size": f"{width}x{height}",
        "hand_mean_error_mm": mm["hand"], "hand_mean_error_mm_dlt": mm["hand_dlt"],
        "hand_mean_error_mm_robust_triangulation_only": mm["hand_tri"],
        "hand_error_ratio_dlt_over_ours": round(mm["hand_dlt"] / mm["hand"], 2),
        "hand_median_error_mm": round(1000 * float(np.median(acc["hand"])), 2),
        "hand_p95_error_mm": round(1000 * float(np.percentile(acc["hand"], 95)), 2),
        "object_mean_error_mm": mm["obj"], "object_mean_error_mm_dlt": mm["obj_dlt"],
        "reprojection_px": round(float(np.mean(acc["reproj"])), 2),
        "reprojection_px_dlt": round(float(np.mean(acc["reproj_dlt"])), 2),
        "coverage": {k: round(float(np.mean(v)), 3) for k, v in cover.items()},
        "hands_fitted_fraction": round(float(np.mean(fitted)), 3),
        "stage_ms_median": {k: round(1000 * float(np.median(v)), 2) for k, v in times.items()},
        "reconstruct_cpu_ms_median": round(1000 * float(np.median(cpu)), 2),
        "reconstruct_ms_median": round(1000 * float(np.median(np.sum([times[k] for k in
                                                                      ("triangulate", "fit_hands", "fit_objects")],
                                                                     axis=0))), 2),
    }


def decode_ms(width: int, height: int, seed: int = 7301) -> float:
    """Median time to decode one frame set's 7 JPEG images (full frames, quality 80 as camhub)."""
    from services.world.render import SceneRenderer, snapshot  # GL only for this one frame set

    sim = WorldSim("assembly", seed=seed)
    sim.step(int(2.0 / sim.physics_dt))
    renderer = SceneRenderer("assembly", width, height)
    images = renderer.render(snapshot(sim.task, sim.data, sim.robot_name, seed, sim.demo, sim.teacher.tactile_hand))
    renderer.close()
    blobs = [encode_jpeg(img, 80) for img in images]
    model = CameraModel(np.zeros((3, 4)), width, height)
    runs = []
    for _ in range(30):
        t0 = time.perf_counter()
        for b in blobs:
            decode_window(b, model)
        runs.append(time.perf_counter() - t0)
    return round(1000 * float(np.median(runs)), 2)


def run_images(args: argparse.Namespace) -> dict:
    """The learned detector on rendered sessions: live, offline, aniposelib, simulated beside."""
    from services.recon.learned_detector import DEFAULT_WEIGHTS_DIR, LearnedDetector  # torch/onnx: this row only

    det = LearnedDetector(args.weights or DEFAULT_WEIGHTS_DIR, object_views=args.object_views,
                          object_reuse=not args.no_object_reuse,
                          object_present_confidence=args.object_present_confidence,
                          object_verify_shift=args.object_verify_shift, object_busy_m=args.object_busy_m,
                          threads=args.threads, precision=args.precision)
    stage_keys = ("decode", "detect", "triangulate", "fit_hands", "fit_objects", "cpu_detect", "cpu_reconstruct")
    times = {k: [] for k in stage_keys}
    load_before = images.load_average()
    seeds = [int(v) for v in args.image_seeds.split(",")] if args.image_seeds else \
        list(IMAGE_SESSIONS[:args.image_sessions])
    sessions = images.run_sessions(det, seeds, "assembly", args.frames, args.rate, 256, 192, times)
    load_after = images.load_average()
    P = np.stack([projection(c.K, c.world_T_cam) for c in camera_specs(256, 192)])

    def pooled(select, which: str) -> dict:
        err = {k: [] for k in images.ERROR_KEYS}
        reproj, rays = [], []
        for s in sessions[:select]:
            recs = getattr(s, which)
            e = images.errors(recs, s)
            for k in err:
                err[k] += e[k]
            r, d = images.geometry(recs, s.uv if which == "live" else s.sim_uv, P)
            reproj += r
            rays += d
        return images.summary(err, reproj, rays)

    out = {"weights": args.weights or "models/detector (shipped)", "runtime": det.runtime, "precision": det.precision,
           "trained": {k: det.meta.get(k) for k in ("iterations", "train_seconds", "images", "input_size")},
           "trained_hand_stage": {k: det.hand_meta.get(k) for k in ("iterations", "train_seconds", "input_size")}
           if det.hand_meta else None,
           "trained_object_stage": {k: det.object_meta.get(k) for k in ("iterations", "train_seconds", "input_size")}
           if det.object_meta else None,
           "object_stage": {"views_per_object": args.object_views, "resting_reused": not args.no_object_reuse,
                            "crops_per_frame_set": round(det.object_crops / max(len(times["detect"]), 1), 2),
                            "objects_cropped": det.schedule.refreshed, "objects_reused": det.schedule.reused,
                            "objects_kept_in_place": det.schedule.kept_in_place,
                            "present_confidence": det.object_present_confidence,
                            "crops_dropped_as_missed": det.object_crops_missed,
                            "verify_shift_half_sides": det.object_verify_shift,
                            "crops_dropped_as_unsteady": det.object_crops_unsteady,
                            "busy_m": det.object_busy_m}
           if det.object_meta else None,
           "sessions": [f"assembly:{s}" for s in seeds], "frames_per_session": args.frames, "size": "256x192",
           "learned_live": pooled(len(sessions), "live"), "simulated_live": pooled(len(sessions), "sim_live")}
    total = np.sum([times[k] for k in ("decode", "detect", "triangulate", "fit_hands", "fit_objects")], axis=0)
    cpu = np.sum([times[k] for k in ("decode", "cpu_detect", "cpu_reconstruct")], axis=0)  # decode: 1 thread
    out["p6"] = {"stage_ms_median": {k: round(1000 * float(np.median(v)), 2) for k, v in times.items()},
                 "frame_set_ms_median": round(1000 * float(np.median(total)), 2),
                 "frame_set_ms_p90": round(1000 * float(np.percentile(total, 90)), 2),
                 "frame_set_cpu_ms_median": round(1000 * float(np.median(cpu)), 2),
                 "load_average_before_after": [load_before, load_after], "cpus": os.cpu_count()}
    print("P6 per 7-camera frame set (ms, medians):", images.dump(out["p6"]))
    print("learned, live:", images.dump(out["learned_live"]))
    print("simulated, live:", images.dump(out["simulated_live"]))
    n_off = min(args.offline_sessions, len(sessions))
    if n_off:
        errs = {k: [] for k in images.ERROR_KEYS}
        live_same = {k: [] for k in errs}
        seconds = 0.0
        for s in sessions[:n_off]:
            recs, sec = images.offline(s, P, "assembly", args.rate)
            seconds += sec
            for k, v in images.errors(recs, s).items():
                errs[k] += v
            for k, v in images.errors(s.live, s).items():
                live_same[k] += v
        out["learned_offline"] = {**images.summary(errs, [], []), "sessions": n_off,
                                  "live_on_the_same_sessions_mm": images.mm(live_same["hand"]),
                                  "seconds_per_session": round(seconds / n_off, 1)}
        print("learned, offline:", images.dump(out["learned_offline"]))
    n_an = min(args.anipose_sessions, len(sessions))
    if n_an:
        cut = [images.first_frames(s, args.anipose_frames) for s in sessions[:n_an]]
        res = images.anipose(cut, P, 256, 192, Path(args.anipose_python))
        if isinstance(res, str):
            out["aniposelib"] = {"not_run": res}
        else:
            row = {"sessions": n_an, "frames_per_session": len(cut[0].uv)}
            for name in ("ransac", "optim"):
                errs, cover = [], []
                for i, s in enumerate(cut):
                    e, c = images.point_errors(res[f"{name}_{i}"], s)
                    errs += e
                    cover.append(c)
                row[f"{name}_hand_mean_error_mm"] = images.mm(errs)
                row[f"{name}_hand_median_error_mm"] = round(1000 * float(np.median(errs)), 2)
                row[f"{name}_coverage"] = round(float(np.mean(cover)), 3)
                row[f"{name}_seconds"] = round(float(sum(res[f"seconds_{i}"][0 if name == "ransac" else 1]
                                                         for i in range(n_an))), 1)
            ours = {k: [] for k in images.ERROR_KEYS}
            for s in cut:
                for k, v in images.errors(s.live, s).items():
                    ours[k] += v
            row["ours_live_hand_mean_error_mm"] = images.mm(ours["hand"])
            row["ratio_ransac_over_ours_live"] = round(row["ransac_hand_mean_error_mm"] / row[
                "ours_live_hand_mean_error_mm"], 2)
            row["ratio_optim_over_ours_live"] = round(row["optim_hand_mean_error_mm"] / row[
                "ours_live_hand_mean_error_mm"], 2)
            out["aniposelib"] = row
        print("aniposelib:", images.dump(out["aniposelib"]))
    return out


def merged(kept: dict, new: dict) -> dict:
    """``kept`` (the file as it was) updated with what this run measured, ``new``: its keys replace
    theirs, dictionaries key by key, so the parts skipped this run and the keys other benches
    added to the file stay."""
    out = dict(kept)
    for k, v in new.items():
        out[k] = merged(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sessions", type=int, default=len(SESSIONS))
    parser.add_argument("--frames", type=int, default=60, help="frame sets per session")
    parser.add_argument("--rate", type=float, default=5.0, help="frame sets per second (the deployment's)")
    parser.add_argument("--noise", type=float, default=1.5, help="pixel noise (px, standard deviation)")
    parser.add_argument("--dropout", type=float, default=0.08)
    parser.add_argument("--outliers", type=float, default=0.03)
    parser.add_argument("--out", default=".bench/recon.json")
    parser.add_argument("--weights", default="", help="the learned detector's (default: the shipped models/detector)")
    parser.add_argument("--threads", type=int, default=2, help="the detector's intra-op threads (recon's)")
    parser.add_argument("--precision", default="auto", choices=PRECISIONS,
                        help="the detector graphs' (auto: the int8 copies where `xm detector quantize` made them)")
    parser.add_argument("--object-views", type=int, default=3,
                        help="views the object stage crops per object, its best (0: every view)")
    parser.add_argument("--no-object-reuse", action="store_true",
                        help="crop every object on every frame set (default: a resting object every other one)")
    parser.add_argument("--object-present-confidence", type=float, default=None,
                        help="the object stage's crops with a weaker mean confidence are dropped (default: the "
                             "detector's, object_crops.PRESENT_CONFIDENCE; 0: off)")
    parser.add_argument("--object-verify-shift", type=float, default=0.3,
                        help="a kept object-stage crop under object_crops.TRUSTED is checked by a twin shifted this "
                             "many half sides (0: off)")
    parser.add_argument("--object-busy-m", type=float, default=0.1,
                        help="an object a hand's centre is this near is cropped every frame set (0: off)")
    parser.add_argument("--image-sessions", type=int, default=len(IMAGE_SESSIONS),
                        help="rendered sessions for the learned detector (0: none)")
    parser.add_argument("--image-seeds", default="",
                        help="WorldSim seeds of the rendered sessions instead (e.g. the validation sessions 7311,7313 "
                             "on which recon's confidence thresholds are chosen)")
    parser.add_argument("--offline-sessions", type=int, default=2,
                        help="of those, refined offline (about a minute per session and hand)")
    parser.add_argument("--anipose-sessions", type=int, default=1, help="of those, triangulated by aniposelib")
    parser.add_argument("--anipose-frames", type=int, default=30,
                        help="its first frame sets (aniposelib's RANSAC tries every subset of views per point "
                             "in Python: about 0.1 s of CPU per point)")
    parser.add_argument("--anipose-python", default=str(images.ANIPOSE_PYTHON),
                        help="the aniposelib venv's python (bench/calibration.py makes it)")
    parser.add_argument("--live", type=float, default=60.0,
                        help="seconds of a live xm up of deploy/sim.toml: recon keeping up with camhub (0: skip)")
    parser.add_argument("--no-projected", action="store_true", help="skip the projected-truth rows")
    args = parser.parse_args()
    learned = run_images(args) if args.image_sessions > 0 else None
    live = _recon_live.live(args.live) if args.live > 0 else None
    if live is not None:
        print("live:", images.dump(live))
    rows = []
    for w, h in ([] if args.no_projected else SIZES):
        row = run(w, h, args)
        row["stage_ms_median"]["decode"] = decode_ms(w, h)
        rows.append(row)
        print(json.dumps(row))
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    kept = json.loads(out.read_text()) if out.exists() else {}
    out.write_text(json.dumps(merged(kept, {
        "sessions": [f"{task}:{seed}" for seed, task in SESSIONS[:args.sessions]], "frames_per_session": args.frames,
        "rate_hz": args.rate, "detections": {"pixel_noise_px": args.noise, "dropout": args.dropout,
                                             "outliers": args.outliers, "occlusion": "the world's estimate"},
        "targets": {"hand_mean_error_mm": 8.0, "hand_mean_error_mm_offline": 5.0, "object_mean_error_mm": 3.0,
                    "detect_plus_reconstruct_ms": 50.0, "aniposelib_over_ours": 1.3,
                    "thesis": {"reprojection_px": 1.8, "ray_deviation_mm": 0.2}},
        "images": learned or {},
        "live": live or {},
        "rows": rows or kept.get("rows", []),
        "note": "errors in mm against truth on the keypoints each method reports (coverage: their share); "
                "stage times are wall-clock medians per 7-camera frame set on a shared 2-core machine "
                "(reconstruct_cpu_ms: the process's CPU time for triangulation and fits, less at the "
                "mercy of neighbours); "
                "in rows, 'detect' is the simulated detector; in images, the learned one. ray_deviation_mm: the mean "
                "distance from a triangulated point to the rays of its inlier views"}), indent=1) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
