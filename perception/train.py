"""``xm detector train``: the U-Net of services/recon/learned_detector.py on a labelled set
(perception/labels.py), with augmentation (perception/augment.py), Adam and a cosine learning
rate, under a wall-clock budget. Writes weights.pt (a state dict, loaded with
``weights_only=True``), meta.json, loss.png and model.onnx (for ONNX Runtime) to the output
folder."""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from tqdm import tqdm  # noqa: E402

from perception.augment import AugmentParams, sample  # noqa: E402
from perception.labels import Frame, keypoint_classes, keypoint_names, read_coco  # noqa: E402
from services.recon.learned_detector import INPUT_SIZE, TRAINING_DIR, UNet  # noqa: E402

SIGMA = 1.5  # heatmap Gaussian, network pixels
FOREGROUND_WEIGHT = 30.0  # heatmap pixels near a keypoint weigh this much more: most of a map is empty
# Share of first-stage samples cut from a full frame at a labelled window's size where no hand is
# (off by default: it teaches the network to report no hand there, docs/perception.md, but did not
# lower the closed-loop error).
EMPTY_WINDOWS = 0.0
MIN_HAND_KEYPOINTS = 4  # a cut with fewer labelled hand keypoints than this counts as showing no hand
CUT_TRIES = 8


def load_set(folder: Path) -> tuple[str, list[Frame], list[np.ndarray]]:
    task, frames = read_coco(folder / "labels.json")
    images = []
    for fr in frames:
        img = cv2.imread(str(folder / fr.file_name), cv2.IMREAD_COLOR)
        if img is None:
            raise FileNotFoundError(f"{folder / fr.file_name}: missing or unreadable image")
        images.append(cv2.cvtColor(img, cv2.COLOR_BGR2RGB))
    return task, frames, images


def stage_parser(prog: str, description: str, stem: str) -> argparse.ArgumentParser:
    """The options every second-stage trainer shares (``xm detector train-hands``, ``train-objects``)."""
    p = argparse.ArgumentParser(prog=prog, description=description)
    p.add_argument("--labels", default=str(TRAINING_DIR / "labels" / "train"), help="labelled set folder")
    p.add_argument("--out", default=str(TRAINING_DIR), help=f"{stem}.pt, {stem}.json, {stem}_loss.png, {stem}.onnx")
    p.add_argument("--minutes", type=float, default=10.0, help="wall-clock budget")
    p.add_argument("--iters", type=int, default=8000)
    p.add_argument("--batch", type=int, default=16)
    p.add_argument("--lr", type=float, default=2e-3)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--seed", type=int, default=0)
    return p


def stage_set(a: argparse.Namespace) -> tuple[str, list[Frame], list[np.ndarray]] | None:
    """Torch set up for a stage's training and its labelled set loaded; None (after saying how to
    make one) when ``a.labels`` holds none."""
    torch.set_num_threads(a.threads)
    torch.set_flush_denormal(True)  # denormal weights late in training slow CPU convolutions many times
    folder = Path(a.labels)
    if not (folder / "labels.json").exists():
        print(f"no labelled set at {folder}; make one with `xm detector label`")
        return None
    return load_set(folder)


def heatmap_loss(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    return ((pred - target) ** 2 * (1.0 + FOREGROUND_WEIGHT * target)).mean()


Sampler = Callable[[np.random.Generator], tuple[np.ndarray, np.ndarray]]  # one (input, targets) pair


def is_full(frame: Frame) -> bool:
    return tuple(frame.roi[2:]) == tuple(frame.full_size)


def cut_window(frame: Frame, image: np.ndarray, side: tuple[int, int], hand_channels: int,
               rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A window of ``side`` (w, h) cut from a full frame where it shows no hand, if one of
    CUT_TRIES random places does (else the last tried): its image, keypoints (window pixels) and
    visibility (0 outside the cut)."""
    H, W = image.shape[:2]
    w, h = min(side[0], W), min(side[1], H)
    for _ in range(CUT_TRIES):
        x0, y0 = int(rng.integers(0, W - w + 1)), int(rng.integers(0, H - h + 1))
        uv = frame.uv - (x0, y0)
        inside = np.all((uv >= -0.5) & (uv <= np.array([w, h]) - 0.5), axis=1)
        vis = np.where(inside, frame.visibility, 0)
        if (vis[:hand_channels] > 0).sum() < MIN_HAND_KEYPOINTS:
            break
    return image[y0:y0 + h, x0:x0 + w], uv, vis


def window_sampler(frames: list[Frame], images: list[np.ndarray], size: tuple[int, int],
                   aug: AugmentParams, empty: float = EMPTY_WINDOWS, hand_channels: int = 0) -> Sampler:
    """Whole labelled window images, letterboxed and augmented (the first stage's input); a share
    ``empty`` of them cut from the full frames where no hand is (the first ``hand_channels``
    keypoints are the hands')."""
    full = [i for i, fr in enumerate(frames) if is_full(fr)]
    sides = [tuple(fr.roi[2:]) for fr in frames if not is_full(fr)]
    if not (full and sides and hand_channels):
        empty = 0.0

    def one(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        if rng.random() < empty:
            i = full[rng.integers(0, len(full))]
            img, uv, vis = cut_window(frames[i], images[i], sides[rng.integers(0, len(sides))], hand_channels, rng)
            return sample(img, uv, vis, size, SIGMA, aug, rng)
        i = rng.integers(0, len(frames))
        return sample(images[i], frames[i].uv, frames[i].visibility, size, SIGMA, aug, rng)
    return one


def batch(sampler: Sampler, n: int, rng: np.random.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    xs, ys = zip(*(sampler(rng) for _ in range(n)), strict=True)
    return torch.from_numpy(np.stack(xs)), torch.from_numpy(np.stack(ys))


def train(frames: list[Frame], images: list[np.ndarray], n_keypoints: int, size: tuple[int, int] = INPUT_SIZE,
          iters: int = 100_000, minutes: float = 10.0, batch_size: int = 8, lr: float = 2e-3, seed: int = 0,
          aug: AugmentParams | None = None, progress: bool = True, device: str = "cpu",
          sampler: Sampler | None = None, init: dict | None = None) -> tuple[UNet, list[float], float]:
    """Trains until ``iters`` iterations or ``minutes`` of wall time; returns the net, the loss per
    iteration and the seconds spent. ``sampler`` draws the training pairs (default: whole windows);
    ``init``: a state dict to start from (default: random)."""
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    sampler = sampler or window_sampler(frames, images, size, aug or AugmentParams())
    net = UNet(n_keypoints)
    if init is not None:
        net.load_state_dict(init)
    net = net.to(device)
    opt = torch.optim.Adam(net.parameters(), lr=lr)
    losses: list[float] = []
    start = time.monotonic()
    budget = minutes * 60.0
    bar = tqdm(total=iters if iters < 100_000 else None, desc="train", unit="it", disable=not progress)
    net.train()
    for it in range(iters):
        elapsed = time.monotonic() - start
        if elapsed > budget:
            break
        # Cosine decay over whichever ends first: the iterations or the time budget.
        frac = max(it / iters, elapsed / budget)
        for g in opt.param_groups:
            g["lr"] = lr * 0.5 * (1 + np.cos(np.pi * min(frac, 1.0)))
        x, y = batch(sampler, batch_size, rng)
        loss = heatmap_loss(net(x.to(device)), y.to(device))
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
        bar.update(1)
        bar.set_postfix(loss=f"{np.mean(losses[-20:]):.4f}", lr=f"{opt.param_groups[0]['lr']:.1e}")
    bar.close()
    net.eval()
    return net.cpu(), losses, time.monotonic() - start


def graph_weights(path: Path) -> dict[str, torch.Tensor] | None:
    """A U-Net's state dict read back from its exported ONNX graph (the initializers carry the
    parameters' names); None when there is no graph. The shipped networks are graphs only."""
    if not path.exists():
        return None
    import onnx  # the exported graph's format: only to read a start from it
    from onnx import numpy_helper

    return {i.name: torch.from_numpy(numpy_helper.to_array(i).copy()) for i in onnx.load(str(path)).graph.initializer}


def plot_losses(losses: list[float], path: Path) -> None:
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.plot(losses, lw=0.6, alpha=0.5, label="batch")
    k = max(1, len(losses) // 50)
    if len(losses) >= k:
        smooth = np.convolve(losses, np.ones(k) / k, mode="valid")
        ax.plot(np.arange(len(smooth)) + k - 1, smooth, lw=1.5, label=f"mean of {k}")
    ax.set_yscale("log")
    ax.set_xlabel("iteration")
    ax.set_ylabel("weighted heatmap MSE")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def export_onnx(net: UNet, size: tuple[int, int], path: Path) -> bool:
    """The graph for ONNX Runtime (any batch size); False when the onnx package is missing."""
    try:
        import onnx  # noqa: F401  (optional: only needed to write the graph)
    except ImportError:
        return False
    dummy = torch.zeros(1, 3, size[1], size[0])
    torch.onnx.export(net, dummy, str(path), input_names=["image"], output_names=["heatmaps"],
                      dynamic_axes={"image": {0: "views"}, "heatmaps": {0: "views"}}, dynamo=False)
    return True


def save(net: UNet, task: str, size: tuple[int, int], losses: list[float], seconds: float, out: Path,
         extra: dict) -> None:
    out.mkdir(parents=True, exist_ok=True)
    torch.save(net.state_dict(), out / "weights.pt")
    meta = {"task": task, "keypoints": keypoint_names(task), "input_size": list(size), "sigma": SIGMA,
            "iterations": len(losses), "train_seconds": round(seconds, 1),
            "final_loss": float(np.mean(losses[-20:])) if losses else None, **extra}
    (out / "meta.json").write_text(json.dumps(meta, indent=1))
    plot_losses(losses, out / "loss.png")
    onnx_path = out / "model.onnx"
    onnx_path.unlink(missing_ok=True)  # never leave a graph of other weights beside these
    export_onnx(net, size, onnx_path)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="xm detector train", description=__doc__.splitlines()[0])
    p.add_argument("--labels", default=str(TRAINING_DIR / "labels" / "train"), help="labelled set folder")
    p.add_argument("--out", default=str(TRAINING_DIR), help="weights.pt, meta.json, loss.png, model.onnx")
    p.add_argument("--minutes", type=float, default=10.0, help="wall-clock budget")
    p.add_argument("--iters", type=int, default=100_000)
    p.add_argument("--batch", type=int, default=8)
    p.add_argument("--lr", type=float, default=2e-3)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--size", default=f"{INPUT_SIZE[0]}x{INPUT_SIZE[1]}", help="network input WxH (multiples of 8)")
    p.add_argument("--device", default="cpu", help="torch device (cpu; cuda where one exists)")
    p.add_argument("--empty-windows", type=float, default=EMPTY_WINDOWS,
                   help="share of samples cut from full frames where no hand is")
    p.add_argument("--init", default="", help="start from the weights of this folder's model.onnx (default: random)")
    a = p.parse_args(argv)
    size = tuple(int(v) for v in a.size.split("x"))
    if len(size) != 2 or any(v % 8 for v in size):
        p.error("--size: WxH, both multiples of 8")
    torch.set_num_threads(a.threads)
    folder = Path(a.labels)
    if not (folder / "labels.json").exists():
        print(f"no labelled set at {folder}; make one with `xm detector label`")
        return 2
    task, frames, images = load_set(folder)
    names = keypoint_names(task)
    print(f"{len(frames)} labelled images of task {task!r}, {len(names)} keypoints, input {size}")
    init = graph_weights(Path(a.init) / "model.onnx") if a.init else None
    if a.init and init is None:
        print(f"--init {a.init}: no model.onnx there to start from")
        return 2
    hands = int((keypoint_classes(task) == "hand").sum())
    sampler = window_sampler(frames, images, size, AugmentParams(), a.empty_windows, hands)
    net, losses, seconds = train(frames, images, len(names), size, a.iters, a.minutes, a.batch, a.lr, a.seed,
                                 device=a.device, sampler=sampler, init=init)
    save(net, task, size, losses, seconds, Path(a.out),
         {"labels": str(folder), "images": len(frames), "batch": a.batch, "lr": a.lr, "threads": a.threads,
          "device": a.device, "empty_windows": a.empty_windows, "init": a.init or "random"})
    print(f"{len(losses)} iterations in {seconds:.0f} s, loss {losses[0]:.4f} -> {np.mean(losses[-20:]):.4f}; "
          f"wrote {a.out}/weights.pt, meta.json, loss.png, model.onnx")
    return 0
