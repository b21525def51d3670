"""`xm simulate`: neural simulation of a trained policy from a start state (recursive rollout)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="xm simulate", description="Roll a trained policy out from the start "
                                     "state of a teacher demonstration; writes the rollout (.npz) and a plot.")
    parser.add_argument("checkpoint", help="policy.pt written by xm train")
    parser.add_argument("--seed", type=int, default=1234, help="layout seed of the start state")
    parser.add_argument("--seconds", type=float, default=8.0)
    parser.add_argument("--out", default="runs/simulate")
    args = parser.parse_args(argv)
    if not Path(args.checkpoint).exists():
        print(f"error: {args.checkpoint} not found (train one with `xm train --teacher 3`)", file=sys.stderr)
        return 2
    from services.policy.metrics import trajectory_scores
    from services.policy.ours import Ours
    from services.world.teacher import generate_demo

    method = Ours.load(args.checkpoint)
    start = generate_demo("assembly", args.seed)
    steps = int(args.seconds / method.dt)
    hands, objects = method.rollout(start, steps)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(out / "rollout.npz", hands=hands, objects=objects, object_names=start.object_names)
    scores = trajectory_scores(hands, objects, start)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 6))
    for h, color in ((0, "tab:red"), (1, "tab:blue")):
        ax.plot(hands[:, h, 8, 0], hands[:, h, 8, 1], color=color, label=f"{('left', 'right')[h]} index (policy)")
        ax.plot(start.hands[:, h, 8, 0], start.hands[:, h, 8, 1], "--", color=color, alpha=0.5, label="teacher")
    ax.plot(objects[:, :, 0], objects[:, :, 1], "g.", ms=1)
    ax.axis("equal")
    ax.legend(fontsize=7)
    ax.set_title(f"neural simulation: hand {scores['hand'] * 1e3:.0f} mm, object {scores['object'] * 1e3:.0f} mm")
    fig.savefig(out / "rollout.png", dpi=110)
    print(f"wrote {out / 'rollout.npz'} and {out / 'rollout.png'}; distance to the teacher: "
          f"hand {scores['hand'] * 1e3:.1f} mm, object {scores['object'] * 1e3:.1f} mm")
    return 0
