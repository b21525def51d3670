"""`xm eval`: the Table 7.1 protocol on the simulated assembly task.

15 teacher demonstrations (3 train: two with the glove on the grasping hand, one on the pressing
hand; 12 validation); every method is fitted on the train set and rolled out (neural or open-loop
simulation) from each validation start state; distances as in services/policy/metrics.py.
Writes results.json, results.md and results.png into --out.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from services.policy.metrics import trajectory_scores
from services.world.teacher import assembly_protocol

METHODS = ["multimodal", "no_tactile", "single_state", "time_window", "dmp", "promp_conditional", "promp_simple",
           "naive"]
TABLE_ROWS = {"multimodal": "(1) Multimodal", "no_tactile": "(2) No tactile", "single_state": "(3) Single state",
              "time_window": "(4) Time window", "dmp": "(5) DMP", "promp_conditional": "(6) Conditional ProMP",
              "promp_simple": "(7) Simple ProMP", "naive": "(10) None (naive replay)"}


def make_method(name: str, steps: int):
    from services.policy.baselines import DMPBaseline, ProMPBaseline
    from services.policy.naive import NaiveReplay
    from services.policy.ours import PRESETS, Ours

    if name in PRESETS:
        cfg = PRESETS[name]
        return Ours(type(cfg)(**{**cfg.__dict__, "steps": steps}))
    return {"dmp": DMPBaseline, "promp_conditional": lambda: ProMPBaseline(True),
            "promp_simple": lambda: ProMPBaseline(False), "naive": NaiveReplay}[name]()


def evaluate(seed: int, methods: list[str], out: Path, steps: int, progress: bool = True) -> dict:
    import torch
    from tqdm import tqdm

    torch.set_num_threads(2)
    demos = assembly_protocol(seed)
    train = [d for d in demos if d.meta["split"] == "train"]
    val = [d for d in demos if d.meta["split"] == "validation"]
    results, timing, examples = {}, {}, {}
    for name in tqdm(methods, desc="methods", disable=not progress):
        method = make_method(name, steps)
        t0 = time.perf_counter()
        method.fit(train, progress=progress)
        fit_s = time.perf_counter() - t0
        scores = []
        for demo in val:
            hands, objects = method.rollout(demo, demo.steps)
            scores.append(trajectory_scores(hands, objects, demo))
        examples[name] = (hands, objects, demo)
        results[name] = {k: float(np.mean([s[k] for s in scores])) for k in scores[0]}
        timing[name] = fit_s
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(json.dumps(results, indent=2))
    (out / "results.md").write_text(table(results, seed, timing))
    plot(results, examples, out / "results.png")
    return results


def table(results: dict, seed: int, timing: dict) -> str:
    ref = results.get("multimodal")
    lines = [f"Table 7.1 protocol, simulated assembly task, seed {seed} (metres; lower is better)", "",
             "| method | hand | object | hand (masked) | object (masked) | fit s |", "|---|---|---|---|---|---|"]
    for name, r in results.items():
        cells = [f"{r[k]:.4f}" + (f" ({r[k] / ref[k]:.1f}x)" if ref and name != "multimodal" else "")
                 for k in ("hand", "object", "hand_masked", "object_masked")]
        lines.append(f"| {TABLE_ROWS.get(name, name)} | " + " | ".join(cells) + f" | {timing[name]:.0f} |")
    return "\n".join(lines) + "\n"


def plot(results: dict, examples: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(14, 5))
    names = list(results)
    x = np.arange(len(names))
    for i, key in enumerate(("hand", "object", "hand_masked", "object_masked")):
        ax.bar(x + (i - 1.5) * 0.2, [results[n][key] for n in names], 0.2, label=key)
    ax.set_xticks(x, [TABLE_ROWS.get(n, n) for n in names], rotation=30, ha="right")
    ax.set_yscale("log")
    ax.set_ylabel("closest-point distance (m)")
    ax.legend()
    ax.set_title("Table 7.1 protocol (simulated assembly)")
    for name, (hands, _objects, demo) in examples.items():
        g = 0 if demo.meta["grasp_hand"] == "left" else 1
        ax2.plot(hands[:, g, 8, 0], hands[:, g, 8, 1], label=name, lw=1)
    ref = demo.hands[:, g, 8]
    ax2.plot(ref[:, 0], ref[:, 1], "k--", lw=2, label="validation demo")
    ax2.set_title("grasping index fingertip, last validation demo (top view)")
    ax2.axis("equal")
    ax2.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="xm eval", description=__doc__.split("\n\n")[0])
    parser.add_argument("--task", default="assembly", choices=["assembly"])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="runs/eval", help="output directory")
    parser.add_argument("--methods", default=",".join(METHODS), help=f"comma-separated subset of {METHODS}")
    parser.add_argument("--steps", type=int, default=2500, help="training steps of the neural methods")
    parser.add_argument("--quick", action="store_true", help="tiny training budget (smoke test)")
    args = parser.parse_args(argv)
    methods = [m for m in args.methods.split(",") if m]
    unknown = sorted(set(methods) - set(METHODS))
    if unknown:
        print(f"error: unknown method(s) {unknown}; known: {METHODS}", file=sys.stderr)
        return 2
    results = evaluate(args.seed, methods, Path(args.out), 20 if args.quick else args.steps)
    print((Path(args.out) / "results.md").read_text())
    return 0 if results else 1
