"""``xm detector eval``: the trained detector on a held-out labelled set (other seeds: other
layouts, teachers' looks and lighting). Per keypoint class (hand, object): mean pixel error in
full-image pixels and PCK@5px over the labelled keypoints; detection rate (confidence at or above
the threshold and within 5 px) of visible and of occluded keypoints; false detections (confidence
at or above the threshold on keypoints outside the window). Writes ``accuracy`` into
.bench/detector.json (bench/detector.py writes ``speed`` beside it)."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import cv2
import numpy as np

from perception.labels import Frame, keypoint_classes
from perception.train import load_set
from services.recon.detector import CameraModel
from services.recon.learned_detector import DEFAULT_WEIGHTS_DIR, TRAINING_DIR, LearnedDetector, View
from services.recon.onnx_graphs import PRECISIONS

PCK_PX = 5.0
THRESHOLD = 0.3


def views_of(frames: list[Frame], images: list[np.ndarray]) -> list[View]:
    # Detection needs only the window and the image; P matters to triangulation, not here.
    return [View(fr.camera, CameraModel(np.zeros((3, 4)), fr.full_size[0], fr.full_size[1], tuple(fr.roi)), img)
            for fr, img in zip(frames, images, strict=True)]


def metrics(uv: np.ndarray, conf: np.ndarray, truth: np.ndarray, vis: np.ndarray, classes: np.ndarray,
            threshold: float = THRESHOLD, pck_px: float = PCK_PX) -> dict:
    """uv/truth (F, N, 2) full-image pixels, conf (F, N), vis (F, N) COCO flags, classes (N,)."""
    err = np.linalg.norm(uv - truth, axis=-1)
    hit = (conf >= threshold) & (err <= pck_px)
    out = {}
    for cls in ("hand", "object", "all"):
        sel = np.ones(len(classes), bool) if cls == "all" else classes == cls
        lab, v2, v1, v0 = vis[:, sel] > 0, vis[:, sel] == 2, vis[:, sel] == 1, vis[:, sel] == 0
        e, c, h = err[:, sel], conf[:, sel], hit[:, sel]

        def frac(x: np.ndarray, m: np.ndarray) -> float | None:
            return round(float(x[m].mean()), 4) if m.any() else None

        out[cls] = {"labelled": int(lab.sum()), "visible": int(v2.sum()), "occluded": int(v1.sum()),
                    "mean_px_error": round(float(e[lab].mean()), 2) if lab.any() else None,
                    "median_px_error": round(float(np.median(e[lab])), 2) if lab.any() else None,
                    "mean_px_error_visible": round(float(e[v2].mean()), 2) if v2.any() else None,
                    "pck5": frac(e <= pck_px, lab), "pck5_visible": frac(e <= pck_px, v2),
                    "detection_rate_visible": frac(h, v2), "detection_rate_occluded": frac(h, v1),
                    "false_detection_rate": frac(c >= threshold, v0)}
    return out


def draw(frames: list[Frame], images: list[np.ndarray], uv: np.ndarray, conf: np.ndarray, path: Path,
         count: int = 7, zoom: int = 3) -> None:
    """A sheet of held-out windows: labels (green: visible, blue: occluded) and detections at or
    above the threshold (red), joined to their label by a line."""
    tiles = []
    rows = list(zip(frames, images, uv, conf, strict=True))
    windows = [r for r in rows if tuple(r[0].roi[2:]) != tuple(r[0].full_size)]  # windows show the hands large
    for fr, img, u, c in (windows or rows)[:count]:
        tile = cv2.resize(cv2.cvtColor(img, cv2.COLOR_RGB2BGR), None, fx=zoom, fy=zoom, interpolation=cv2.INTER_NEAREST)
        off = np.array(fr.roi[:2], float)
        to_px = lambda p: tuple(int(round(v)) for v in (np.asarray(p) + 0.5) * zoom - 0.5)  # noqa: E731
        for k in range(len(fr.uv)):
            if fr.visibility[k]:
                cv2.circle(tile, to_px(fr.uv[k]), 3, (0, 200, 0) if fr.visibility[k] == 2 else (255, 120, 0), -1)
            if c[k] >= THRESHOLD:
                if fr.visibility[k]:
                    cv2.line(tile, to_px(fr.uv[k]), to_px(u[k] - off), (0, 0, 255), 1)
                cv2.drawMarker(tile, to_px(u[k] - off), (0, 0, 255), cv2.MARKER_CROSS, 7, 1)
        tiles.append(cv2.resize(tile, (288, 216)))
    cv2.imwrite(str(path), np.hstack(tiles))


def swap_hands(uv: np.ndarray, conf: np.ndarray, truth: np.ndarray, vis: np.ndarray,
               per_hand: int = 21) -> tuple[np.ndarray, np.ndarray]:
    """uv and conf with the two hands' channels exchanged in every image where that brings the
    detections closer to the labels: the error left when which hand is which is not asked."""
    n = 2 * per_hand
    swapped_uv, swapped_conf = uv.copy(), conf.copy()
    swapped_uv[:, :n] = np.concatenate([uv[:, per_hand:n], uv[:, :per_hand]], axis=1)
    swapped_conf[:, :n] = np.concatenate([conf[:, per_hand:n], conf[:, :per_hand]], axis=1)
    lab = vis[:, :n] > 0
    err = lambda u: np.where(lab, np.linalg.norm(u[:, :n] - truth[:, :n], axis=-1), 0.0).sum(axis=1)  # noqa: E731
    better = err(swapped_uv) < err(uv)
    return np.where(better[:, None, None], swapped_uv, uv), np.where(better[:, None], swapped_conf, conf)


def evaluate(weights: Path, labels: Path, runtime: str = "auto", png: Path | None = None,
             precision: str = "auto") -> dict:
    det = LearnedDetector(weights, runtime=runtime, precision=precision)
    task, frames, images = load_set(labels)
    if det.meta["task"] != task:
        raise ValueError(f"detector trained for task {det.meta['task']!r}, labels are of {task!r}")
    t0 = time.perf_counter()
    uv, conf = [], []
    for i in range(0, len(frames), 7):  # frame-set sized batches, as recon calls it
        u, c = det.detect(views_of(frames[i:i + 7], images[i:i + 7]))
        uv.append(u)
        conf.append(c)
    seconds = time.perf_counter() - t0
    uv, conf = np.concatenate(uv), np.concatenate(conf)
    truth = np.stack([fr.uv + [fr.roi[0], fr.roi[1]] for fr in frames])
    vis = np.stack([fr.visibility for fr in frames])
    if png is not None:
        draw(frames, images, uv, conf, png)
    classes = keypoint_classes(task)
    any_side = metrics(*swap_hands(uv, conf, truth, vis), truth, vis, classes)["hand"]
    return {"labels": str(labels), "images": len(frames), "runtime": det.runtime, "precision": det.precision,
            "threshold": THRESHOLD,
            "pck_px": PCK_PX, "trained": {k: det.meta.get(k) for k in ("iterations", "train_seconds", "images",
                                                                        "input_size", "device")},
            "seconds_per_image": round(seconds / len(frames), 4),
            **metrics(uv, conf, truth, vis, classes), "hand_either_side": any_side}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="xm detector eval", description=__doc__.splitlines()[0])
    p.add_argument("--weights", default=str(DEFAULT_WEIGHTS_DIR), help="default: the shipped network")
    p.add_argument("--labels", default=str(TRAINING_DIR / "labels" / "eval"), help="held-out labelled set")
    p.add_argument("--runtime", default="auto", choices=("auto", "onnx", "torch"))
    p.add_argument("--precision", default="auto", choices=PRECISIONS,
                   help="ONNX Runtime's graphs (auto: the int8 copies where `xm detector quantize` made them)")
    p.add_argument("--out", default=".bench/detector.json")
    p.add_argument("--png", help="also draw the first held-out windows with labels and detections to this PNG")
    a = p.parse_args(argv)
    result = evaluate(Path(a.weights), Path(a.labels), a.runtime, Path(a.png) if a.png else None, a.precision)
    print(f"held-out set {a.labels}: {result['images']} window images, runtime {result['runtime']} "
          f"({', '.join(f'{k} {v}' for k, v in result['precision'].items())}), detector "
          f"trained {result['trained']['iterations']} iterations / {result['trained']['train_seconds']} s")
    print(f"{'class':>7} {'labelled':>8} {'mean px':>8} {'median':>7} {'PCK@5':>6} {'det vis':>8} {'det occ':>8} "
          f"{'false':>6}")
    for cls in ("hand", "object", "all", "hand_either_side"):
        r, label = result[cls], cls.replace("_either_side", "*")
        print(f"{label:>7} {r['labelled']:>8} {r['mean_px_error']!s:>8} {r['median_px_error']!s:>7} {r['pck5']!s:>6} "
              f"{r['detection_rate_visible']!s:>8} {r['detection_rate_occluded']!s:>8} "
              f"{r['false_detection_rate']!s:>6}")
    print("hand*: the same with left and right exchanged where that fits the labels better (which hand is which "
          "not asked)")
    out = Path(a.out)
    doc = json.loads(out.read_text()) if out.exists() else {}
    # The float graphs' figures stand beside the int8 ones recon runs.
    doc["accuracy_float32" if a.precision == "float32" else "accuracy"] = result
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(doc, indent=1))
    print(f"wrote {out}")
    return 0
