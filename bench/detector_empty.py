"""How confidently the detector reports a hand where there is none: windows cut from the held-out
full frames where no hand keypoint is labelled (the first stage) and hand-sized crops placed away
from every hand (the second stage), as a window left behind by a jump shows them. Per network
folder: the median over windows of the median hand-channel confidence, and the share of windows
at or above the network's hand-present threshold (recon's). Writes ``empty`` into .bench/detector.json.

    python bench/detector_empty.py [models/detector runs/detector ...]

Without a held-out labelled set it renders one first, as `xm detector label` does (seconds).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from perception import sim_labels
from perception.augment import NO_AUGMENT
from perception.hand_stage import MIN_LABELLED, empty_sample, hand_half
from perception.train import cut_window, is_full, load_set
from services.recon.learned_detector import (
    DEFAULT_WEIGHTS_DIR,
    HAND_INPUT,
    TRAINING_DIR,
    LearnedDetector,
    peaks,
    to_input,
)
from shared.demo import HAND_NAMES, KEYPOINTS_PER_HAND

HANDS = len(HAND_NAMES) * KEYPOINTS_PER_HAND


def empty_inputs(folder: Path, tries: int, seed: int) -> tuple[list[np.ndarray], np.ndarray]:
    """Window images that show no hand, and a batch of hand crops that show none."""
    _, frames, images = load_set(folder)
    full = [i for i, f in enumerate(frames) if is_full(f)]
    sides = [tuple(f.roi[2:]) for f in frames if not is_full(f)]
    if not full or not sides:
        raise SystemExit(f"{folder}: needs full frames and windows (`xm detector label` makes both)")
    rng = np.random.default_rng(seed)
    windows, crops = [], []
    for _ in range(tries):
        i = full[rng.integers(len(full))]
        img, _, vis = cut_window(frames[i], images[i], sides[rng.integers(len(sides))], HANDS, rng)
        if not (vis[:HANDS] > 0).any():
            windows.append(img)
        fr = frames[i]
        h = int(rng.integers(len(HAND_NAMES)))
        sl = slice(h * KEYPOINTS_PER_HAND, (h + 1) * KEYPOINTS_PER_HAND)
        if (fr.visibility[sl] > 0).sum() >= MIN_LABELLED:
            half = hand_half(fr.uv[sl], fr.visibility[sl] > 0, rng)
            crops.append(empty_sample(images[i], fr.uv[:HANDS], fr.visibility[:HANDS] > 0, half, HAND_INPUT,
                                      NO_AUGMENT, rng)[0])
    return windows, np.ascontiguousarray(np.stack(crops), dtype=np.float32)


def measure(weights: str, windows: list[np.ndarray], crops: np.ndarray) -> dict:
    d = LearnedDetector(weights)
    first = []
    for img in windows:
        batch, _ = to_input([img], d.size)
        _, conf = peaks(d.heatmaps(batch))
        first += [float(np.median(conf[0, sl])) for sl in d.hand_slices]
    present = d.hand_present_confidence
    out = {"precision": d.precision, "threshold": present, "first_stage_windows": len(windows),
           "first_stage_median_confidence": round(float(np.median(first)), 3),
           "first_stage_share_present": round(float(np.mean(np.array(first) >= present)), 3)}
    hand_maps = d.hand_heatmaps(crops)
    if hand_maps is not None:
        _, conf = peaks(hand_maps)
        per_crop = np.median(conf, axis=1)
        out.update({"hand_stage_crops": len(crops),
                    "hand_stage_median_confidence": round(float(np.median(per_crop)), 3),
                    "hand_stage_share_present": round(float(np.mean(per_crop >= present)), 3)})
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("weights", nargs="*", default=[str(DEFAULT_WEIGHTS_DIR)],
                   help="network folders (default: the shipped one; a training run's folder)")
    p.add_argument("--labels", default=str(TRAINING_DIR / "labels" / "eval"), help="held-out labelled set")
    p.add_argument("--tries", type=int, default=120)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=".bench/detector.json")
    a = p.parse_args()
    labels = Path(a.labels)
    if not (labels / "labels.json").exists():
        if labels.name != "eval":
            raise SystemExit(f"no labelled set at {labels}; make one with `xm detector label`")
        sim_labels.main(["--out", str(labels.parent), "--frames", "0"])
    windows, crops = empty_inputs(Path(a.labels), a.tries, a.seed)
    rows = {w: measure(w, windows, crops) for w in a.weights}
    for w, r in rows.items():
        print(w, r)
    out = Path(a.out)
    kept = json.loads(out.read_text()) if out.exists() else {}
    kept["empty"] = {"labels": a.labels, "networks": rows}
    out.write_text(json.dumps(kept, indent=1))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
