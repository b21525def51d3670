"""Where recon's object error comes from, on the held-out rendered sessions of bench/recon.py.

Per object keypoint: how many views' windows hold it and how many of those see it (line of sight),
its size in the network's input pixels, the learned detector's 2-D error per view (confident
detections, visible and hidden), how often the detection is on another keypoint of the same
object (the symmetric board's corners), the robust triangulation's error and inlier views, and the
reported error. Beside it, recon's stages on the same windows with projected truth (no noise) in
the views that see each keypoint: the floor of the 3-D stages and a check that truth, calibration
and images agree. Writes .bench/recon_objects.json.
"""

from __future__ import annotations

import argparse
import json
import pickle
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # runnable as a script from anywhere
sys.path.insert(0, str(Path(__file__).resolve().parent))  # its helper module

import _recon_images as images  # noqa: E402

from services.recon.learned_detector import DEFAULT_WEIGHTS_DIR, INPUT_SIZE, LearnedDetector  # noqa: E402
from services.recon.objects import task_keypoint_names  # noqa: E402
from services.recon.pipeline import Reconstructor  # noqa: E402
from services.recon.triangulation import project  # noqa: E402
from services.world.model import camera_specs  # noqa: E402
from shared.demo import KEYPOINTS_PER_HAND  # noqa: E402
from shared.geometry import projection  # noqa: E402

THRESHOLD = images.THRESHOLD
NH = 2 * KEYPOINTS_PER_HAND


def q(values: list | np.ndarray, fn=np.mean, scale: float = 1.0) -> float | None:
    v = np.asarray(values, float)
    return round(float(fn(v)) * scale, 2) if v.size else None


def breakdown(sessions: list, P: np.ndarray, names: list[str], task: str) -> dict:
    per = {n: {k: [] for k in ("in_window", "visible", "px_err", "px_err_visible", "px_err_hidden", "conf",
                               "other_kp", "net_scale", "tri_err", "tri_views", "tri_reported", "err",
                               "oracle_err")} for n in names}
    sizes = {"board": [], "camera": []}
    oracle_objects = []
    for s in sessions:
        oracle = Reconstructor(task)
        for t in range(len(s.truth)):
            truth = s.truth[t][NH:]
            pix, depth = project(P, truth)  # (C,K,2), (C,K)
            roi = s.rois[t]
            lo, hi = roi[:, None, :2], roi[:, None, :2] + roi[:, None, 2:]
            inside = (depth > 0) & np.all((pix >= lo) & (pix < hi), axis=-1)
            hidden = s.hidden[t]
            visible = inside & ~hidden
            scale = np.minimum(INPUT_SIZE[0] / roi[:, 2], INPUT_SIZE[1] / roi[:, 3])  # network px per image px
            uv, conf = s.uv[t][:, NH:], s.conf[t][:, NH:]
            err2d = np.linalg.norm(uv - pix, axis=-1)
            # nearest keypoint of the same object to each detection (is it another one's?)
            r = s.live[t]
            # oracle: projected truth in the views that see the point, no noise
            o_uv = np.concatenate([s.uv[t][:, :NH], pix], axis=1)
            o_conf = np.concatenate([s.conf[t][:, :NH], visible.astype(float)], axis=1)
            o = oracle.step(P, o_uv, o_conf, roi)
            oracle_objects.append(o)
            for c in range(len(P)):
                for obj, sl in (("board", slice(0, 4)), ("camera", slice(5, 8))):
                    if inside[c, sl].all():
                        ext = pix[c, sl]
                        sizes[obj].append(float(np.linalg.norm(ext.max(0) - ext.min(0)) * scale[c]))
            for k, n in enumerate(names):
                d = per[n]
                d["in_window"].append(int(inside[:, k].sum()))
                d["visible"].append(int(visible[:, k].sum()))
                ok = inside[:, k] & (conf[:, k] >= THRESHOLD)
                d["px_err"] += list(err2d[ok, k])
                d["px_err_visible"] += list(err2d[ok & ~hidden[:, k], k])
                d["px_err_hidden"] += list(err2d[ok & hidden[:, k], k])
                d["conf"] += list(conf[inside[:, k], k])
                d["net_scale"] += list(scale[inside[:, k]])
                same = [j for j, m in enumerate(names) if m.split("/")[0] == n.split("/")[0] and j != k]
                for c in np.flatnonzero(ok):
                    others = np.linalg.norm(pix[c, same] - uv[c, k], axis=-1)
                    d["other_kp"].append(bool(others.min() < err2d[c, k] and err2d[c, k] > 2.0))
                tri_ok = r.inliers[:, NH + k].sum() >= 2
                d["tri_reported"].append(bool(tri_ok))
                if tri_ok:
                    d["tri_err"].append(float(np.linalg.norm(r.triangulated[NH + k] - truth[k])))
                    d["tri_views"].append(int(r.inliers[:, NH + k].sum()))
                if r.object_mask[k]:
                    d["err"].append(float(np.linalg.norm(r.objects[k] - truth[k])))
                if o.object_mask[k]:
                    d["oracle_err"].append(float(np.linalg.norm(o.objects[k] - truth[k])))
    out = {}
    for n, d in per.items():
        px = np.asarray(d["px_err"])
        out[n] = {"views_in_window": q(d["in_window"]), "views_seeing": q(d["visible"]),
                  "network_px_per_image_px": q(d["net_scale"]),
                  "confident_share": q(np.asarray(d["conf"]) >= THRESHOLD),
                  "px_median": q(px, np.median), "px_mean": q(px),
                  "within_2px": q(px < 2), "within_5px": q(px < 5),
                  "px_median_visible": q(d["px_err_visible"], np.median),
                  "px_median_hidden": q(d["px_err_hidden"], np.median),
                  "hidden_share_of_confident": round(len(d["px_err_hidden"]) / max(len(px), 1), 3),
                  "on_another_keypoint_of_the_object": q(d["other_kp"]),
                  "triangulated_share": q(d["tri_reported"]),
                  "triangulated_mm_median": q(d["tri_err"], np.median, 1000),
                  "triangulated_mm_mean": q(d["tri_err"], np.mean, 1000),
                  "triangulated_over_2cm": q(np.asarray(d["tri_err"]) > 0.02),
                  "triangulated_inlier_views": q(d["tri_views"]),
                  "reported_mm_mean": q(d["err"], np.mean, 1000),
                  "reported_mm_median": q(d["err"], np.median, 1000),
                  "oracle_mm_mean": q(d["oracle_err"], np.mean, 1000)}
    out["object_extent_network_px"] = {k: q(v, np.median) for k, v in sizes.items()}
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sessions", type=int, default=4)
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--weights", default="")
    parser.add_argument("--out", default=".bench/recon_objects.json")
    parser.add_argument("--keep", default="", help="also pickle the sessions (detections, truth) here")
    args = parser.parse_args()
    det = LearnedDetector(args.weights or DEFAULT_WEIGHTS_DIR)
    times = {k: [] for k in ("decode", "detect", "triangulate", "fit_hands", "fit_objects", "cpu_detect",
                             "cpu_reconstruct")}
    t0 = time.perf_counter()
    seeds = [7301, 7303, 7305, 7307][:args.sessions]
    sessions = images.run_sessions(det, seeds, "assembly", args.frames, 5.0, 256, 192, times, occlusion=True)
    if args.keep:
        with open(args.keep, "wb") as f:
            pickle.dump(sessions, f)
    P = np.stack([projection(c.K, c.world_T_cam) for c in camera_specs(256, 192)])
    names = task_keypoint_names("assembly")
    out = {"sessions": seeds, "frames": args.frames, "weights": args.weights or "models/detector",
           "per_keypoint": breakdown(sessions, P, names, "assembly"),
           "seconds": round(time.perf_counter() - t0, 1)}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=1) + "\n")
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
