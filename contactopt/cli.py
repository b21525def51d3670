"""`xm contactopt train --task turn_cube`: optimize a contact-based policy (progress bar, learning
curve PNG, result JSON, weights); `xm contactopt bench`: Gauss-Newton against SGD and Adam at
several learning rates, same wall-clock budget and same batches, written to .bench/contactopt.json
and as a table into docs/contactopt.md."""

from __future__ import annotations

import argparse
import json
import os
import sys
from dataclasses import asdict
from pathlib import Path

import torch

from contactopt.tasks import ALL_TASKS, TASKS, get_task
from contactopt.train import OPTIMIZERS, Result, plot_curves, train

DOC = Path("docs/contactopt.md")
BENCH = Path(".bench/contactopt.json")
BEGIN, END = "<!-- bench:begin -->", "<!-- bench:end -->"
LRS = {"sgd": (1e-3, 1e-2, 1e-1), "adam": (1e-4, 1e-3, 1e-2)}


def train_main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="xm contactopt train", description=__doc__)
    ap.add_argument("--task", required=True, help=f"one of: {', '.join(ALL_TASKS)}")
    ap.add_argument("--optimizer", default="gn", choices=OPTIMIZERS)
    ap.add_argument("--lr", type=float, default=None, help="learning rate (sgd, adam)")
    ap.add_argument("--budget", type=float, default=600.0, help="training seconds (see --clock)")
    ap.add_argument("--clock", default="wall", choices=("wall", "cpu"),
                    help="budget in wall-clock or in this process's CPU seconds (shared host)")
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
    policy, result = train(task, args.optimizer, args.lr, args.budget, args.batch, args.seed, clock=args.clock)
    args.out.mkdir(parents=True, exist_ok=True)
    stem = args.out / f"{task.name}_{args.optimizer}"
    plot_curves([result], f"{stem}.png")
    torch.save(policy.state_dict(), f"{stem}.pt")
    Path(f"{stem}.json").write_text(json.dumps(asdict(result), indent=1))
    ev = result.evaluation
    print(f"{task.name} {args.optimizer}: {result.iterations} iterations in {result.seconds:.0f} s, "
          f"metric {ev['metric']:.3g} (goal {ev['goal']:.3g}), in the MuJoCo replay {ev['replay_metric']:.3g} "
          f"(final position error {ev['replay_position_error_mm']:.1f} mm, rotation "
          f"{ev['replay_rotation_error_deg']:.1f} deg), success {result.success} (in MuJoCo "
          f"{result.replay_success}); {stem}.png")
    return 0


def fmt(ev: dict, key: str, spec: str = ".3g") -> str:
    return "-" if key not in ev else format(ev[key], spec)


def yes_no(flag: bool | None) -> str:
    return "-" if flag is None else ("yes" if flag else "no")


def table(results: list[dict]) -> str:
    """The comparison table from result dicts (as stored in .bench/contactopt.json)."""
    rows = ["| task | optimizer | lr | iterations | final batch loss | metric (goal) | distance loss | "
            "gap at the forces [mm] | MuJoCo replay: metric / position error [mm] / rotation error [deg] | "
            "success | criterion met in MuJoCo |",
            "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        ev = r["evaluation"]
        last = r["curve"][-1][1] if r["curve"] else float("nan")
        lr = "-" if r["lr"] is None else f"{r['lr']:g}"
        metric = ev.get("metric", ev.get("turn_velocity"))
        goal = ev.get("goal", TASKS[r["task"]].omega_goal if r["task"] in TASKS else float("nan"))
        rows.append(f"| {r['task']} | {r['optimizer']} | {lr} | {r['iterations']} | {last:.3g} | "
                    f"{metric:.3g} ({goal:.3g}) | {ev['distance']:.3g} | {ev['force_weighted_gap_mm']:.3g} | "
                    f"{fmt(ev, 'replay_metric')} / {fmt(ev, 'replay_position_error_mm', '.1f')} / "
                    f"{fmt(ev, 'replay_rotation_error_deg', '.1f')} | {'yes' if r['success'] else 'no'} | "
                    f"{yes_no(r.get('replay_success'))} |")
    return "\n".join(rows)


def thin(result: dict, points: int = 200) -> dict:
    """A result with its learning curve cut to at most `points` entries (the JSON stays small)."""
    curve = result["curve"]
    step = max(1, -(-len(curve) // points))
    return {**result, "curve": curve[::step] + ([curve[-1]] if (len(curve) - 1) % step else [])}


def bench_main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="xm contactopt bench", description=__doc__)
    ap.add_argument("--tasks", default=",".join(ALL_TASKS))
    ap.add_argument("--budget", type=float, default=120.0, help="training seconds per run (see --clock)")
    ap.add_argument("--clock", default="wall", choices=("wall", "cpu"),
                    help="budget in wall-clock or in this process's CPU seconds (shared host)")
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
        task_results = [train(task, o, lr, args.budget, args.batch, args.seed, clock=args.clock)[1]
                        for o, lr in runs]
        plot_curves(task_results, f"docs/contactopt_{task.name}.png")
        results += task_results
    # the stored results of the tasks not run now are kept: one table over every task benched
    stored = json.loads(BENCH.read_text()) if BENCH.exists() else {}
    runs_by_task = stored.get("runs", {})
    for r in stored.get("results", []):  # a file of one bench run: its results, by task
        run = runs_by_task.setdefault(r["task"], {k: stored.get(k) for k in ("budget_s", "batch", "seed")})
        run.setdefault("results", []).append(r)
    for task in tasks:
        runs_by_task[task.name] = {"budget_s": args.budget, "clock": args.clock, "batch": args.batch, "seed": args.seed,
                                   "load_average": load_average(),
                                   "results": [thin(asdict(r)) for r in results if r.task == task.name]}
    ordered = {n: runs_by_task[n] for n in ALL_TASKS if n in runs_by_task}
    BENCH.parent.mkdir(exist_ok=True)
    BENCH.write_text(json.dumps({"runs": ordered}, indent=1))
    text = table([r for run in ordered.values() for r in run["results"]])
    doc = DOC.read_text()
    if BEGIN in doc and END in doc:
        head, rest = doc.split(BEGIN, 1)
        DOC.write_text(f"{head}{BEGIN}\n{text}\n{END}{rest.split(END, 1)[1]}")
    print(text)
    return 0


def load_average() -> float:
    """The host's one-minute load average when a task's runs end (timings depend on it)."""
    return os.getloadavg()[0]


def main(argv: list[str]) -> int:
    commands = {"train": train_main, "bench": bench_main}
    if not argv or argv[0] not in commands:
        print("usage: xm contactopt {train,bench} [options]  (--help after a command for its options)",
              file=sys.stderr)
        return 2
    return commands[argv[0]](argv[1:])
