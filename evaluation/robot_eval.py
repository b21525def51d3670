"""`xm eval --execute --task NAME`: the robot loop of one task, the learned policy alone beside the
policy with contact anchors, on the validation layouts of the net's seed and on the validation
layouts of held-out seeds (never used to choose any constant of the loop).

assembly and latch run evaluation/execute.py (latch: the snap-fit needs its 5 N), pick_place and
wiping evaluation/execute_carry.py. bottle has no robot loop: the cap's thread is not modelled in
MuJoCo, so robot mode has no physical test of it; `--execute --task bottle` says so. The anchors
are mined from the training demonstrations of the net's seed (evaluation/anchors.py,
evaluation/carry.py) and used on every seed's layouts. ``learned`` runs without anchors
(hand feedback stays: it is what the robot observes of itself), ``anchored`` with them.
Writes execute.json (every layout) and execute.md (the table) into --out.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from evaluation.anchors import AnchorError, mine_anchors
from evaluation.carry import mine_carry_anchors
from evaluation.execute import execute_layout
from evaluation.execute_carry import CARRY_TASKS, execute_carry
from evaluation.reconstructed import CellObserver, ReconOptions, ReconstructionError, held_objects, reconstructed_demos
from services.policy.model import Policy, PolicyError
from services.world.tasks import TASKS
from services.world.tasks import task as task_spec
from services.world.teacher import object_names

LOOP_TASKS = tuple(name for name, spec in TASKS.items() if spec.executable)  # the registry's
NO_LOOP = {"bottle": "the cap's thread is not modelled in MuJoCo, so robot mode has no physical test of the "
                     "bottle (docs/tasks.md); its Table 7.1 protocol runs with `xm eval --task bottle`"}
VARIANTS = ("learned", "anchored")
ANCHOR_MOVED_M = 0.01  # reconstructed demonstrations: a grasped object has moved 1 cm (their noise is mm)


class ExecuteError(ValueError):
    """A robot-loop request that cannot run (task without a loop, wrong checkpoint, no anchors)."""


def check_task(task: str) -> None:
    """Raises ExecuteError naming the tasks with a robot loop, or why ``task`` has none."""
    if task not in TASKS:
        raise ExecuteError(f"unknown task {task!r}; known tasks: {', '.join(TASKS)}")
    if task in NO_LOOP:
        raise ExecuteError(f"task {task!r} has no robot loop: {NO_LOOP[task]}; robot loops: {', '.join(LOOP_TASKS)}")
    if task not in LOOP_TASKS:
        raise ExecuteError(f"task {task!r} has no robot mapping; robot loops: {', '.join(LOOP_TASKS)}")


def check_model(model, task: str) -> None:
    """A checkpoint trained on another task observes other objects: refused with both lists."""
    if model is None:
        return
    want = object_names(task)
    if list(model.object_names) != list(want):
        raise ExecuteError(f"the checkpoint observes objects {model.object_names}, task {task!r} has {want}: "
                           f"give a net trained with `xm eval --task {task}`")


def anchors_for(task: str, seed: int, recon: ReconOptions | None = None, recon_cache: str = "runs/recon_demos",
                progress: bool = False):
    """The contact anchors of ``task`` mined from the training demonstrations of ``seed``."""
    spec = task_spec(task)
    demos = spec.protocol(seed)
    if recon is not None:
        demos = reconstructed_demos(demos, task, seed, recon, recon_cache, progress)
    train = demos[:spec.train]
    try:
        if task in CARRY_TASKS:
            return mine_carry_anchors(task, train)
        return mine_anchors([held_objects(d) for d in train], moved_m=ANCHOR_MOVED_M) if recon else mine_anchors(train)
    except AnchorError as exc:
        raise ExecuteError(f"no contact anchors in the training demonstrations of {task} seed {seed} ({exc}); "
                           "run --variants learned") from exc


def run_layout(model, task: str, seed: int, demo: int, anchors, feedback: bool, catch_m: float | None,
               recon: ReconOptions | None = None, start_hands: np.ndarray | None = None) -> dict:
    """One layout of ``task``: the loop's record as a dict with at least ``success``."""
    if task in CARRY_TASKS:
        return execute_carry(model, task, seed, demo, anchors, feedback=feedback, catch_m=catch_m).to_dict()
    observer = CellObserver(task, seed, demo, recon) if recon else None
    try:
        return execute_layout(model, seed, demo, feedback=feedback, anchors=anchors, catch_m=catch_m,
                              observer=observer, start_hands=start_hands, task=task).to_dict()
    finally:
        if observer is not None:
            observer.close()


def run_execute(model, task: str, seed: int, held_out: list[int], layouts: int, variants: tuple[str, ...],
                feedback: bool = True, catch_m: float | None = 0.03, progress: bool = False,
                recon: ReconOptions | None = None, recon_cache: str = "runs/recon_demos") -> dict:
    """Every (seed, variant) row of the robot loop of ``task``: {rows: [...], anchors: ...}."""
    check_task(task)
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown:
        raise ExecuteError(f"unknown variant(s) {unknown}; known: {', '.join(VARIANTS)}")
    if recon is not None and task in CARRY_TASKS:
        raise ExecuteError(f"--observations reconstructed runs the assembly's loop only, not {task!r}")
    check_model(model, task)
    spec = task_spec(task)
    anchors = anchors_for(task, seed, recon, recon_cache, progress) if "anchored" in variants else None
    rows = []
    for s in [seed, *held_out]:
        starts = None
        if recon is not None:  # the policy starts from the reconstructed start hands
            starts = reconstructed_demos(spec.protocol(s), task, s, recon, recon_cache, progress)
        for variant in variants:
            records = []
            for demo in tqdm(range(spec.train, spec.train + min(layouts, spec.validation)),
                             desc=f"{task} seed {s} {variant}", disable=not progress):
                hands0 = starts[demo].hands[0].astype(float) if starts is not None else None
                records.append(run_layout(model, task, s, demo, anchors if variant == "anchored" else None,
                                          feedback, catch_m, recon, hands0))
                if not progress:
                    print(f"{task} seed {s} {variant} layout {demo}: success {records[-1]['success']}", flush=True)
            rows.append({"seed": s, "layouts": "validation" if s == seed else "held-out", "variant": variant,
                         "successes": int(sum(r["success"] for r in records)), "runs": len(records),
                         "success_rate": float(np.mean([r["success"] for r in records])) if records else 0.0,
                         "records": records})
    return {"task": task, "seed": seed, "held_out": held_out, "hand_feedback": feedback,
            "catch_mm": None if catch_m is None else catch_m * 1e3,
            "anchors": anchors.to_dict() if anchors is not None else None, "rows": rows}


def table(result: dict, checkpoint: str) -> str:
    """execute.md: successes per seed, the learned policy alone beside the anchored one."""
    by = {(r["seed"], r["variant"]): r for r in result["rows"]}
    variants = [v for v in VARIANTS if any(k[1] == v for k in by)]
    lines = [f"Robot loop, task {result['task']}, net {checkpoint} (trained on seed {result['seed']}); hand feedback "
             f"{'on' if result['hand_feedback'] else 'off'}; target 90 %", "",
             "| layouts | " + " | ".join({"learned": "learned policy alone", "anchored": "with contact anchors"}[v]
                                       for v in variants) + " |",
             "|---|" + "---|" * len(variants)]
    for s in dict.fromkeys(k[0] for k in by):
        cells = []
        for v in variants:
            r = by.get((s, v))
            cells.append(f"{r['successes']} / {r['runs']} ({100 * r['successes'] / max(r['runs'], 1):.0f} %)"
                         if r else "")
        kind = "validation" if s == result["seed"] else "held-out"
        lines.append(f"| seed {s} ({kind}) | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def execute_main(args: argparse.Namespace) -> int:
    """`xm eval --execute`: success of the robot driven by the learned policy, alone and anchored."""
    try:
        check_task(args.task)
        held_out = [int(s) for s in args.held_out_seeds.split(",") if s.strip()]
        variants = tuple(v.strip() for v in args.variants.split(",") if v.strip())
        if not args.anchors:
            variants = tuple(v for v in variants if v != "anchored") or ("learned",)
    except ExecuteError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except ValueError:
        print(f"error: --held-out-seeds {args.held_out_seeds!r}: expected comma-separated integers", file=sys.stderr)
        return 2
    path = Path(args.checkpoint)
    if args.teacher:
        model, path = None, Path("teacher")
    elif not path.exists():
        print(f"error: no policy checkpoint at {path}; train one with `xm eval --task {args.task}` or `make policy` "
              "and give --checkpoint", file=sys.stderr)
        return 2
    else:
        try:
            model = Policy.load(str(path))
        except (PolicyError, OSError, RuntimeError, KeyError, ValueError) as exc:
            print(f"error: cannot load {path}: {exc}", file=sys.stderr)
            return 2
    torch.set_num_threads(1)
    recon = None
    if args.observations == "reconstructed":
        recon = ReconOptions(detector=args.detector, weights=args.detector_weights, windows=args.recon_windows)
    try:
        result = run_execute(model, args.task, args.seed, held_out, args.layouts, variants, args.hand_feedback,
                             args.catch_mm / 1e3 if args.catch_mm > 0 else None, not args.no_progress, recon,
                             args.recon_cache)
    except (ExecuteError, ReconstructionError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    result["checkpoint"] = str(path)
    result["observations"] = recon.__dict__ if recon else "truth"
    (out / "execute.json").write_text(json.dumps(result, indent=2))
    md = table(result, str(path))
    (out / "execute.md").write_text(md)
    print(md + f"\ndetails in {out / 'execute.json'}")
    return 0
