"""``xm detector train-objects``: the detector's object stage, the same U-Net on one object at a time.

Training pairs are crops of the labelled window images around one object (services/recon/
object_crops.py makes the same crops at run time from the first stage's peaks): the crop's centre
is the median of the object's labelled keypoints displaced by a normal error of 0.15 half sides
per axis (a guess at the run-time centres' error, not measured), its side spans the object crop's
metric size at the scale the labels show (the largest ratio of a labelled pixel distance to the
model's metric distance between two of the object's keypoints, the least foreshortened pair), and
the targets are every object keypoint in the crop (the channel of the cropped object is what
recon reads). Colour, blur, noise, rotation and occluders as for the first stage; no mirroring
(the board's corners differ only by their handedness). Training starts from the first stage's
weights (``--init``). Writes objects.pt, objects.json, objects_loss.png and objects.onnx beside
the first stage's files.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from perception.augment import AugmentParams, augmented_crop
from perception.labels import Frame
from perception.train import SIGMA, Sampler, export_onnx, graph_weights, plot_losses, stage_parser, stage_set, train
from services.recon.learned_detector import OBJECT_INPUT
from services.recon.object_crops import HALF_SIZE_M, object_slices
from services.recon.objects import object_models, task_keypoint_names
from shared.demo import HAND_NAMES, KEYPOINTS_PER_HAND

FIRST = len(HAND_NAMES) * KEYPOINTS_PER_HAND  # object keypoints follow both hands' in the labels
MIN_LABELLED = 2  # labelled keypoints an object needs in a window to be cropped for training
MIN_PAIR_M = 0.01  # keypoint pairs closer than this on the model say little about the scale
# The centre's displacement over the half side (per axis; assumed, not measured at run time) and
# the half side over the labels' scale estimate (foreshortening makes the estimate low, never high).
CENTRE_JITTER = 0.15
HALF_RATIO = (0.9, 1.4)


def object_table(task: str) -> list[tuple[slice, np.ndarray]]:
    """Per object: its rows among the object keypoints and its model points (k,3)."""
    return [(m.slice, m.points) for m in object_models(task)]


def pixels_per_metre(uv: np.ndarray, labelled: np.ndarray, model: np.ndarray) -> float | None:
    idx = np.flatnonzero(labelled)
    best = None
    for a in range(len(idx)):
        for b in range(a + 1, len(idx)):
            metric = float(np.linalg.norm(model[idx[a]] - model[idx[b]]))
            if metric >= MIN_PAIR_M:
                r = float(np.linalg.norm(uv[idx[a]] - uv[idx[b]])) / metric
                best = r if best is None else max(best, r)
    return best


def object_crops(frames: list[Frame], table: list[tuple[slice, np.ndarray]]) -> list[tuple[int, int]]:
    """(frame index, object index) of every object with enough labelled keypoints in its window."""
    out = []
    for i, fr in enumerate(frames):
        vis = fr.visibility[FIRST:]
        for o, (sl, model) in enumerate(table):
            lab = vis[sl] > 0
            if lab.sum() >= MIN_LABELLED and pixels_per_metre(fr.uv[FIRST:][sl], lab, model):
                out.append((i, o))
    return out


def crop_sample(image: np.ndarray, uv: np.ndarray, labelled: np.ndarray, sl: slice, model: np.ndarray, size: int,
                aug: AugmentParams, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """One pair: uv (K,2) window pixels of every object keypoint, labelled (K,) bool; the crop is
    around the object at rows ``sl``. Input (3, size, size), targets (K, size, size)."""
    own = labelled[sl]
    centre = np.median(uv[sl][own], axis=0)
    half = pixels_per_metre(uv[sl], own, model) * HALF_SIZE_M * rng.uniform(*HALF_RATIO)
    centre = centre + rng.normal(0.0, CENTRE_JITTER, 2) * half
    return augmented_crop(image, uv, labelled, centre, half, size, False, aug, SIGMA, rng)


def crop_sampler(frames: list[Frame], images: list[np.ndarray], task: str, size: int, aug: AugmentParams) -> Sampler:
    table = object_table(task)
    pairs = object_crops(frames, table)
    if not pairs:
        raise ValueError("no object with enough labelled keypoints in the set")

    def one(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        i, o = pairs[rng.integers(0, len(pairs))]
        fr = frames[i]
        sl, model = table[o]
        return crop_sample(images[i], fr.uv[FIRST:], fr.visibility[FIRST:] > 0, sl, model, size, aug, rng)
    return one


def first_stage_init(folder: Path, n_obj: int) -> dict[str, torch.Tensor] | None:
    """The first stage's weights (its ONNX graph's initializers, named as the U-Net's parameters)
    as a start for the object stage: the same layers, the head cut to the object channels (the
    last ``n_obj``). None when the folder has no graph."""
    state = graph_weights(Path(folder) / "model.onnx")
    if state is None:
        return None
    state["head.weight"], state["head.bias"] = state["head.weight"][-n_obj:], state["head.bias"][-n_obj:]
    return state


def main(argv: list[str] | None = None) -> int:
    p = stage_parser("xm detector train-objects", __doc__.splitlines()[0], "objects")
    p.add_argument("--init", default="models/detector",
                   help="start from the first stage's weights in this folder (model.onnx; '' for random)")
    a = p.parse_args(argv)
    loaded = stage_set(a)
    if loaded is None:
        return 2
    task, frames, images = loaded
    table = object_table(task)
    n_obj = sum(sl.stop - sl.start for sl, _ in table)
    sampler = crop_sampler(frames, images, task, OBJECT_INPUT, AugmentParams())
    print(f"{len(object_crops(frames, table))} object crops in {len(frames)} labelled images, "
          f"input {OBJECT_INPUT}x{OBJECT_INPUT}")
    init = first_stage_init(Path(a.init), n_obj) if a.init else None
    print("start:", f"the first stage's weights in {a.init}" if init is not None else "random")
    net, losses, seconds = train(frames, images, n_obj, (OBJECT_INPUT, OBJECT_INPUT), a.iters, a.minutes,
                                 a.batch, a.lr, a.seed, sampler=sampler, init=init)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    torch.save(net.state_dict(), out / "objects.pt")
    meta = {"task": task, "keypoints": task_keypoint_names(task), "input_size": OBJECT_INPUT,
            "half_size_m": HALF_SIZE_M, "sigma": SIGMA, "iterations": len(losses), "train_seconds": round(seconds, 1),
            "final_loss": float(np.mean(losses[-20:])) if losses else None, "labels": str(Path(a.labels)),
            "batch": a.batch, "lr": a.lr, "threads": a.threads, "seed": a.seed, "init": a.init or "random",
            "objects": [name for name, _ in object_slices(task_keypoint_names(task), 0)]}
    (out / "objects.json").write_text(json.dumps(meta, indent=1))
    plot_losses(losses, out / "objects_loss.png")
    (out / "objects.onnx").unlink(missing_ok=True)  # never leave a graph of other weights beside these
    export_onnx(net, (OBJECT_INPUT, OBJECT_INPUT), out / "objects.onnx")
    print(f"{len(losses)} iterations in {seconds:.0f} s, loss {losses[0]:.4f} -> {np.mean(losses[-20:]):.4f}; "
          f"wrote {out}/objects.pt, objects.json, objects_loss.png, objects.onnx")
    return 0
