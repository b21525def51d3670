"""`xm train`: fit the chapter-7 policy from recordings (or from teacher demonstrations)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np


def main(argv: list[str] | None = None) -> int:
    from services.policy.ours import PRESETS

    parser = argparse.ArgumentParser(prog="xm train", description="Train the denoising keypoint policy of thesis "
                                     "chapter 7 and write a checkpoint (torch.load(weights_only=True)).")
    parser.add_argument("recordings", nargs="*", help="MCAP recordings (scene + session keys)")
    parser.add_argument("--teacher", type=int, default=0, metavar="N",
                        help="instead: N scripted teacher demonstrations of the assembly task")
    parser.add_argument("--preset", default="multimodal", choices=sorted(PRESETS))
    parser.add_argument("--steps", type=int, default=2500, help="optimizer steps")
    parser.add_argument("--out", default="runs/policy", help="output directory")
    args = parser.parse_args(argv)
    demos = []
    if args.recordings:
        from services.policy.dataset import DatasetError, demos_from_mcap

        for rec in args.recordings:
            if not Path(rec).exists():
                print(f"error: {rec} not found", file=sys.stderr)
                return 2
            try:
                found, warnings = demos_from_mcap(rec)
            except DatasetError as exc:
                print(f"error: {exc}", file=sys.stderr)
                return 2
            for w in warnings:
                print(f"warning: {w}", file=sys.stderr)
            demos += found
    elif args.teacher:
        from services.world.teacher import generate_demo

        demos = [generate_demo("assembly", 9000 + i, index=i) for i in range(args.teacher)]
    if not demos:
        print("error: no demonstrations: give recordings or --teacher N", file=sys.stderr)
        return 2
    import torch

    from services.policy.ours import Ours

    torch.set_num_threads(2)
    cfg = PRESETS[args.preset]
    method = Ours(type(cfg)(**{**cfg.__dict__, "steps": args.steps}))
    method.fit(demos, progress=True)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    method.save(str(out / "policy.pt"))
    losses = np.array(method.losses)
    (out / "train.json").write_text(json.dumps({"demos": len(demos), "steps": args.steps, "preset": args.preset,
                                                "seconds": method.train_seconds,
                                                "final_loss": float(losses[-100:].mean())}, indent=2))
    _plot_losses(losses, out / "loss.png")
    print(f"wrote {out / 'policy.pt'} ({len(demos)} demonstrations, {method.train_seconds:.0f} s); "
          f"loss curve {out / 'loss.png'}")
    return 0


def _plot_losses(losses: np.ndarray, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.semilogy(losses, lw=0.5, alpha=0.4)
    k = max(1, len(losses) // 50)
    ax.semilogy(np.convolve(losses, np.ones(k) / k, mode="valid"), lw=1.5)
    ax.set_xlabel("step")
    ax.set_ylabel("masked MSE")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
