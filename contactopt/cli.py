"""`xm contactopt train --task turn_cube`: optimize a contact-based policy (progress bar, learning
curve PNG, result JSON, weights); `xm contactopt bench`: Gauss-Newton against SGD and Adam at
several learning rates, same wall-clock budget and same batches, written to .bench/contactopt.json
and as a table into docs/contactopt.md."""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict
from pathlib import Path

import torch

from contactopt.tasks import TASKS, get_task
from contactopt.train import OPTIMIZERS, Result, plot_curves, train

DOC = Path("docs/contactopt.md")
BENCH = Path(".bench/contactopt.json")
BEGIN, END = "<!-- bench:begin -->", "<!-- bench:end -->"
LRS = {"sgd": (1e-3, 1e-2, 1e-1), "adam": (1e-4, 1e-3, 1e-2)}


def train_main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="xm contactopt train", description=__doc__)
    ap.add_argument("--task", required=True, help=f"one of: {', '.join(TASKS)}")
    ap.add_argument("--optimizer", default="gn", choices=OPTIMIZERS)
    ap.add_argument("--lr", type=float, default=None, help="learning rate (sgd, adam)")
    ap.add_argument("--budget", type=float, default=600.0, help="training wall-clock seconds")
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=Path("runs/contactopt"))
    args = ap.parse_args(argv)
    try:
        task = get_task(args.task)
    except ValueError as exc:
        print(f"xm contactopt: {exc}", file=sys.stderr)
        return 2
    torch.set_num_threads(1)
    policy, result = train(task, args.optimizer, args.lr, args.budget, args.batch, args.seed)
    args.out.mkdir(parents=True, exist_ok=True)
    stem = args.out / f"{task.name}_{args.optimizer}"
    plot_curves([result], f"{stem}.png")
    torch.save(policy.state_dict(), f"{stem}.pt")
    Path(f"{stem}.json").write_text(json.dumps(asdict(result), indent=1))
    ev = result.evaluation
    print(f"{task.name} {args.optimizer}: {result.iterations} iterations in {result.seconds:.0f} s, "
          f"turn velocity {ev['turn_velocity']:.3f} rad/s (goal {task.omega_goal}), replayed with hard "
          f"contacts {ev['replay_turn_velocity']:.3f}, softplus {ev['replay_softplus_turn_velocity']:.3f}, "
          f"success {result.success}; {stem}.png")
    return 0


def table(results: list[Result]) -> str:
    rows = ["| task | optimizer | lr | iterations | final batch loss | turn velocity [rad/s] | "
            "distance loss | gap at the forces [mm] | replayed: hard / softplus contacts [rad/s] | success |",
            "|---|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        ev = r.evaluation
        last = r.curve[-1][1] if r.curve else float("nan")
        rows.append(f"| {r.task} | {r.optimizer} | {'-' if r.lr is None else f'{r.lr:g}'} | {r.iterations} | "
                    f"{last:.3g} | {ev['turn_velocity']:.3g} | {ev['distance']:.3g} | "
                    f"{ev['force_weighted_gap_mm']:.3g} | {ev['replay_turn_velocity']:.3g} / "
                    f"{ev['replay_softplus_turn_velocity']:.3g} | "
                    f"{'yes' if r.success else 'no'} |")
    return "\n".join(rows)


def thin(result: dict, points: int = 200) -> dict:
    """A result with its learning curve cut to at most `points` entries (the JSON stays small)."""
    curve = result["curve"]
    step = max(1, -(-len(curve) // points))
    return {**result, "curve": curve[::step] + ([curve[-1]] if (len(curve) - 1) % step else [])}


def bench_main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="xm contactopt bench", description=__doc__)
    ap.add_argument("--tasks", default=",".join(TASKS))
    ap.add_argument("--budget", type=float, default=120.0, help="training seconds per run")
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    try:
        tasks = [get_task(n) for n in args.tasks.split(",")]
    except ValueError as exc:
        print(f"xm contactopt: {exc}", file=sys.stderr)
        return 2
    torch.set_num_threads(1)
    results: list[Result] = []
    for task in tasks:
        runs = [("gn", None)] + [(o, lr) for o in ("sgd", "adam") for lr in LRS[o]]
        task_results = [train(task, o, lr, args.budget, args.batch, args.seed)[1] for o, lr in runs]
        plot_curves(task_results, f"docs/contactopt_{task.name}.png")
        results += task_results
    BENCH.parent.mkdir(exist_ok=True)
    BENCH.write_text(json.dumps({"budget_s": args.budget, "batch": args.batch, "seed": args.seed,
                                 "results": [thin(asdict(r)) for r in results]}, indent=1))
    text = DOC.read_text()
    if BEGIN in text and END in text:
        head, rest = text.split(BEGIN, 1)
        DOC.write_text(f"{head}{BEGIN}\n{table(results)}\n{END}{rest.split(END, 1)[1]}")
    print(table(results))
    return 0


def main(argv: list[str]) -> int:
    commands = {"train": train_main, "bench": bench_main}
    if not argv or argv[0] not in commands:
        print("usage: xm contactopt {train,bench} [options]  (--help after a command for its options)",
              file=sys.stderr)
        return 2
    return commands[argv[0]](argv[1:])
