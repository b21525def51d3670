"""``xm detector train-hands``: the detector's second stage, the same U-Net on one hand at a time.

Training pairs are crops of the labelled window images around one hand (services/recon/hand_crops.py
makes the same crops at run time from the first stage's peaks): the crop's centre is the hand's
labelled median displaced as far as the run-time centres are off, its side spans the hand's extent
times the range the run-time metric size gives, left hands are mirrored, and the targets are that
hand's 21 keypoints only (the other hand, often in the crop too, is background). Colour, blur,
noise, rotation and occluders as for the first stage. Writes hands.pt, hands.json, hands_loss.png
and hands.onnx beside the first stage's files.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from perception.augment import AugmentParams, augmented_crop
from perception.labels import Frame
from perception.train import SIGMA, Sampler, export_onnx, graph_weights, plot_losses, stage_parser, stage_set, train
from services.recon.learned_detector import HAND_INPUT
from shared.demo import HAND_NAMES, KEYPOINTS_PER_HAND

MIN_LABELLED = 4  # labelled keypoints a hand needs in a window to be cropped for training
# The run-time crop's half side over the hand's largest keypoint distance from its median, and the
# run-time centre's error over the half side (per axis), as measured on the validation sessions.
EXTENT_RATIO = (0.4, 0.95)
CENTRE_JITTER = 0.12
# Share of crops placed where no hand is, with empty targets, so that this stage says so when the
# first stage placed a hand where there is none (off by default, as EMPTY_WINDOWS).
EMPTY_CROPS = 0.0
EMPTY_TRIES = 8


def hand_crops(frames: list[Frame]) -> list[tuple[int, int]]:
    """(frame index, hand index) of every hand with enough labelled keypoints in its window."""
    out = []
    for i, fr in enumerate(frames):
        for h in range(len(HAND_NAMES)):
            if (fr.visibility[h * KEYPOINTS_PER_HAND:(h + 1) * KEYPOINTS_PER_HAND] > 0).sum() >= MIN_LABELLED:
                out.append((i, h))
    return out


def crop_sample(image: np.ndarray, uv: np.ndarray, labelled: np.ndarray, mirror: bool, size: int,
                aug: AugmentParams, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """One pair: uv (21,2) window pixels, labelled (21,) bool. Input (3, size, size), targets (21, size, size)."""
    half = hand_half(uv, labelled, rng)
    centre = np.median(uv[labelled], axis=0) + rng.normal(0.0, CENTRE_JITTER, 2) * half
    return augmented_crop(image, uv, labelled, centre, half, size, mirror, aug, SIGMA, rng)


def hand_half(uv: np.ndarray, labelled: np.ndarray, rng: np.random.Generator) -> float:
    pts = uv[labelled]
    return max(float(np.abs(pts - np.median(pts, axis=0)).max()), 4.0) / rng.uniform(*EXTENT_RATIO)


def empty_sample(image: np.ndarray, uv: np.ndarray, labelled: np.ndarray, half: float, size: int,
                 aug: AugmentParams, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A crop of a hand's size placed where it holds no labelled hand keypoint (``uv`` (N,2),
    ``labelled`` (N,) of both hands), if one of EMPTY_TRIES random places does; its targets are
    empty whatever it shows."""
    h, w = image.shape[:2]
    for _ in range(EMPTY_TRIES):
        centre = rng.uniform([0.0, 0.0], [w - 1.0, h - 1.0])
        if not np.any(labelled & np.all(np.abs(uv - centre) <= half, axis=1)):
            break
    nothing = np.zeros(KEYPOINTS_PER_HAND, bool)
    return augmented_crop(image, uv[:KEYPOINTS_PER_HAND], nothing, centre, half, size, bool(rng.random() < 0.5),
                          aug, SIGMA, rng)


def crop_sampler(frames: list[Frame], images: list[np.ndarray], size: int, aug: AugmentParams,
                 empty: float = EMPTY_CROPS) -> Sampler:
    """Crops around one labelled hand; a share ``empty`` of them placed where no hand is."""
    pairs = hand_crops(frames)
    if not pairs:
        raise ValueError("no hand with enough labelled keypoints in the set")
    hands = slice(0, len(HAND_NAMES) * KEYPOINTS_PER_HAND)

    def one(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        i, h = pairs[rng.integers(0, len(pairs))]
        fr, sl = frames[i], slice(h * KEYPOINTS_PER_HAND, (h + 1) * KEYPOINTS_PER_HAND)
        if rng.random() < empty:  # a hand's size from this hand, placed where no hand is
            half = hand_half(fr.uv[sl], fr.visibility[sl] > 0, rng)
            return empty_sample(images[i], fr.uv[hands], fr.visibility[hands] > 0, half, size, aug, rng)
        return crop_sample(images[i], fr.uv[sl], fr.visibility[sl] > 0, HAND_NAMES[h] == "left", size, aug, rng)
    return one


def main(argv: list[str] | None = None) -> int:
    p = stage_parser("xm detector train-hands", __doc__.splitlines()[0], "hands")
    p.add_argument("--empty-crops", type=float, default=EMPTY_CROPS, help="share of crops placed where no hand is")
    p.add_argument("--init", default="", help="start from the weights of this folder's hands.onnx (default: random)")
    a = p.parse_args(argv)
    loaded = stage_set(a)
    if loaded is None:
        return 2
    task, frames, images = loaded
    init = graph_weights(Path(a.init) / "hands.onnx") if a.init else None
    if a.init and init is None:
        print(f"--init {a.init}: no hands.onnx there to start from")
        return 2
    sampler = crop_sampler(frames, images, HAND_INPUT, AugmentParams(), a.empty_crops)
    print(f"{len(hand_crops(frames))} hand crops in {len(frames)} labelled images, input {HAND_INPUT}x{HAND_INPUT}")
    net, losses, seconds = train(frames, images, KEYPOINTS_PER_HAND, (HAND_INPUT, HAND_INPUT), a.iters, a.minutes,
                                 a.batch, a.lr, a.seed, sampler=sampler, init=init)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    torch.save(net.state_dict(), out / "hands.pt")
    meta = {"task": task, "keypoints": [str(k) for k in range(KEYPOINTS_PER_HAND)], "input_size": HAND_INPUT,
            "sigma": SIGMA, "mirrored": "left", "iterations": len(losses), "train_seconds": round(seconds, 1),
            "final_loss": float(np.mean(losses[-20:])) if losses else None, "labels": str(Path(a.labels)),
            "batch": a.batch, "lr": a.lr, "threads": a.threads, "seed": a.seed,
            "empty_crops": a.empty_crops, "init": a.init or "random"}
    (out / "hands.json").write_text(json.dumps(meta, indent=1))
    plot_losses(losses, out / "hands_loss.png")
    (out / "hands.onnx").unlink(missing_ok=True)  # never leave a graph of other weights beside these
    export_onnx(net, (HAND_INPUT, HAND_INPUT), out / "hands.onnx")
    print(f"{len(losses)} iterations in {seconds:.0f} s, loss {losses[0]:.4f} -> {np.mean(losses[-20:]):.4f}; "
          f"wrote {out}/hands.pt, hands.json, hands_loss.png, hands.onnx")
    return 0
