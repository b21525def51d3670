"""`xm eval`: the Table 7.1 protocol (thesis 7.6.8) on the simulated assembly task.

15 teacher demonstrations (3 train, 12 validation); every method is fitted on the train set and
rolled out (neural simulation / open loop) from each validation start state; the rollouts are
scored with the symmetric closest-point distance of learning/metrics.py, for hand and
object keypoints, with and without the validation occlusion masks. Writes results.json,
results.md (Table 7.1 layout with ratios to "ours" = multimodal), results.png (grouped bars, log
scale), rollout_<method>.png (one example rollout per method) and rollouts_<method>.npz (every
rollout, so that `xm eval --rescore` recomputes the scores without fitting again) into --out,
for rows (1)-(4) the scored net as policy_<method>.pt (`xm eval --execute --checkpoint`), for the
Diffusion Policy rows their validation curve (curve_<method>.json/.png), and run.json: the run's
seed, draw, settings and per row the code version (evaluation/runs.py), which `--merge` checks.
`--seeds S,... --draws N` runs the grid into --out/seed<S>-draw<D> and summarizes it (summary.md).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import zipfile
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from evaluation.baselines import make
from evaluation.plots import plot_results, plot_rollout
from evaluation.reconstructed import (
    DETECTORS,
    OBSERVATIONS,
    WINDOWS,
    ReconOptions,
    ReconstructionError,
    reconstructed_demos,
    reconstruction_error,
)
from evaluation.robot_eval import VARIANTS, execute_main
from evaluation.runs import RunError, check_merge, run_grid, run_meta
from evaluation.task_measure import measure_table, task_measure
from learning.metrics import SCORE_KEYS, trajectory_scores
from learning.ours import Ours
from learning.presets import PRESETS, config_changes, quick_budget
from services.policy.flat_state import BaselineError
from services.policy.model import PolicyError
from services.world.tasks import TASKS, UnknownTaskError
from services.world.tasks import task as task_spec
from services.world.teacher import assembly_protocol
from shared.demo import Demo

OURS = ("multimodal", "no_tactile")
METHODS = ("multimodal", "no_tactile", "single_state", "time_window", "dmp", "promp_conditional", "promp_simple",
           "diffusion_unet", "diffusion_transformer", "naive")
ROWS = {"multimodal": ("(1) Multimodal", "Yes", "Yes"), "no_tactile": ("(2) No tactile", "No", "Yes"),
        "single_state": ("(3) Single state", "No", "No"), "time_window": ("(4) Time window", "No", "No"),
        "dmp": ("(5) DMP", "No", "No"), "promp_conditional": ("(6) Conditional ProMP", "No", "No"),
        "promp_simple": ("(7) Simple ProMP", "No", "No"), "diffusion_unet": ("(8) LeRobot Diffusion U-Net", "No", "No"),
        "diffusion_transformer": ("(9) Diffusion Transformer", "No", "No"), "naive": ("(10) None", "No", "No")}
REFERENCE = "multimodal"


class EvaluationError(ValueError):
    """Bad evaluation request (unknown method, no validation demonstrations)."""


def make_method(name: str, quick: bool = False, seed: int = 0, draw: int = 0, changes: dict | None = None):
    """A fresh unfitted method by its Table 7.1 name. Rows (1)-(4) are presets of learning/presets.py
    whose ``TrainConfig.seed`` is ``draw``, with ``changes`` to their recipe; the other baselines
    take ``seed``."""
    if name in PRESETS:
        return Ours(quick_budget(PRESETS[name].replace(seed=draw, **(changes or {})), quick))
    return make(name, quick=quick, seed=seed)


def split(demos: list[Demo]) -> tuple[list[Demo], list[Demo]]:
    train = [d for d in demos if d.meta.get("split") == "train"]
    val = [d for d in demos if d.meta.get("split") == "validation"]
    if not train or not val:
        raise EvaluationError(f"need train and validation demos (meta['split']); got {len(train)} / {len(val)}")
    return train, val


def rollouts(method, val: list[Demo], progress: bool, starts: list[Demo] | None = None
             ) -> list[tuple[np.ndarray, np.ndarray]]:
    """One rollout per validation demo, as long as that demo, from its start state as ``starts``
    observe it (default: the demo itself). Batched when the method can."""
    starts = val if starts is None else starts
    if hasattr(method, "rollout_batch"):
        outs = method.rollout_batch(starts, max(d.steps for d in val))
        return [(h[:d.steps], o[:d.steps]) for (h, o), d in zip(outs, val, strict=True)]
    return [method.rollout(s, d.steps) for s, d in tqdm(list(zip(starts, val, strict=True)),
                                                        desc=f"rollout {method.name}", disable=not progress,
                                                        leave=False)]


def score(outs: list[tuple[np.ndarray, np.ndarray]], val: list[Demo]) -> dict[str, float]:
    """Mean over validation demos of each Table 7.1 column; raises if a rollout has a bad shape."""
    per = []
    for (hands, objects), demo in zip(outs, val, strict=True):
        want_h, want_o = (demo.steps, 2, 21, 3), (demo.steps, demo.objects.shape[1], 3)
        if hands.shape != want_h or objects.shape != want_o:
            raise EvaluationError(f"rollout shapes {hands.shape}, {objects.shape}; expected {want_h}, {want_o}")
        if not (np.isfinite(hands).all() and np.isfinite(objects).all()):
            per.append({k: float("inf") for k in SCORE_KEYS})  # a diverged rollout scores infinitely bad
            continue
        per.append(trajectory_scores(hands, objects, demo))
    return {k: float(np.mean([p[k] for p in per])) for k in SCORE_KEYS}


def evaluate(task: str = "assembly", seed: int = 0, methods: list[str] | tuple[str, ...] = METHODS,
             out_dir: str | Path = "runs/eval", quick: bool = False, progress: bool = True,
             demos: list[Demo] | None = None, merge: bool = False, draw: int = 0,
             changes: dict | None = None, recon: ReconOptions | None = None,
             recon_cache: str | Path | None = "runs/recon_demos") -> dict[str, dict[str, float]]:
    """Run the protocol; returns {method: {hand, object, hand_masked, object_masked}} (metres).

    ``demos`` replaces the teacher's 15 (each needs meta['split'] = 'train' | 'validation').
    ``merge`` keeps the other methods' rows of an earlier run in ``out_dir``: only of the same
    experiment (seed, draw, task, budget, observations, recipe changes, code version of each kept
    row: evaluation/runs.py), else EvaluationError. A method whose training fails (non-finite loss)
    scores inf, its reason is kept in run.json's ``failed`` and the run goes on.
    ``draw`` > 0 trains every learned method from other random numbers (initial weights, batches,
    noise): one training run is one draw, and draws of the same recipe differ (docs/policy.md).
    ``changes``: recipe fields changed in rows (1)-(4) (`xm eval --set`).
    ``recon``: every method observes the demonstrations as recon reconstructs them from rendered
    images (evaluation/reconstructed.py; cached in ``recon_cache``): it trains on the reconstructed
    training demonstrations and rolls out from the reconstructed validation start states; the
    scores stay against the validation demonstrations' truth."""
    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        raise EvaluationError(f"unknown method(s) {unknown}; known: {', '.join(METHODS)}")
    try:
        spec = task_spec(task)
    except UnknownTaskError as exc:
        raise EvaluationError(str(exc)) from exc
    # one thread: the summation order of every product is then fixed, and so is the trained net
    # (two threads on two cores trained the seed-0 multimodal row to 29.1 mm instead of 20.5: docs/policy.md)
    torch.set_num_threads(1)
    if demos is None:
        demos = spec.protocol(seed)
    train, val = split(demos)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    observed_train, starts, observed = train, val, "truth"
    if recon is not None:
        try:
            seen = reconstructed_demos(demos, task, seed, recon, recon_cache, progress)
        except (ReconstructionError, FileNotFoundError) as exc:
            raise EvaluationError(f"cannot reconstruct the demonstrations: {exc}") from exc
        observed_train, starts = split(seen)
        observed = f"reconstructed ({recon.detector} detector, {recon.windows} windows, {recon.width}x{recon.height})"
        write_reconstruction(out / "reconstruction.json", recon, observed_train + starts, train + val)
    results, timing = {}, {}
    meta = run_meta(task, seed, draw, quick, observed, changes, methods)
    if merge and (out / "results.json").exists():
        results = json.loads((out / "results.json").read_text())
        kept = [m for m in results if m not in methods]
        try:
            old = check_merge(out, meta, kept)
        except RunError as exc:
            raise EvaluationError(str(exc)) from exc
        results = {m: results[m] for m in kept}
        meta["versions"] = {**{m: old["versions"][m] for m in kept}, **meta["versions"]}
        meta["failed"] = {m: why for m, why in old.get("failed", {}).items() if m in kept}
        timing = json.loads((out / "timing.json").read_text()) if (out / "timing.json").exists() else {}
    measures = {}  # the task's force-decided outcome per method (tasks with a measure)
    train_seed = seed + 1000 * draw  # the other learned baselines' seed; draw 0 keeps the protocol's
    bar = tqdm(list(methods), desc="methods", disable=not progress)
    for name in bar:
        bar.set_postfix(method=name)
        torch.manual_seed(train_seed)
        method = make_method(name, quick=quick, seed=train_seed, draw=draw, changes=changes)
        if hasattr(method, "monitor"):  # the validation curve of a baseline trained for many iterations
            method.monitor = lambda m: score(rollouts(m, val, False, starts), val)
        t0 = time.perf_counter()
        try:
            method.fit(observed_train, progress=progress)
        except (BaselineError, PolicyError) as exc:  # diverged: the row says so, the other rows still run
            results[name], meta["failed"][name] = {k: float("inf") for k in SCORE_KEYS}, str(exc)
            print(f"{name}: training failed: {exc}", file=sys.stderr)
            (out / "run.json").write_text(json.dumps(meta, indent=2))
            continue
        t1 = time.perf_counter()
        if getattr(method, "curve", None):
            method.save_curve(out / f"curve_{name}.json", out / f"curve_{name}.png")
        outs = rollouts(method, val, progress, starts)
        t2 = time.perf_counter()
        results[name] = score(outs, val)
        measure = task_measure(task, method, outs, val, starts)
        if measure is not None:
            measures[name] = measure
            (out / "task_measure.json").write_text(json.dumps({"task": task, "seed": seed, "draw": draw,
                                                               "methods": measures}, indent=2))
        save_rollouts(outs, out / f"rollouts_{name}.npz", seed, quick)
        if hasattr(method, "save"):  # rows (1)-(4): the very net scored, for `xm eval --execute --checkpoint`
            method.save(str(out / f"policy_{name}.pt"))
        timing[name] = {"fit_s": t1 - t0, "rollout_s": t2 - t1}
        results = in_table_order(results)
        plot_rollout(name, outs[0], val[0], out / f"rollout_{name}.png", ROWS.get(name, (name,))[0])
        # written after every method so that a long run leaves partial results behind
        (out / "results.json").write_text(json.dumps(results, indent=2))
        (out / "run.json").write_text(json.dumps(meta, indent=2))
    (out / "timing.json").write_text(json.dumps(timing, indent=2))
    write_tables(out, results, timing, seed, quick, len(train), len(val), draw, changes, observed, task=task)
    if measures:
        with (out / "results.md").open("a") as f:
            f.write(measure_table(task, measures, {k: v[0] for k, v in ROWS.items()}))
    return results


def write_reconstruction(path: Path, options: ReconOptions, seen: list[Demo], truth: list[Demo]) -> None:
    """How far the observed demonstrations are from their truth: per demonstration and on average
    over the training demonstrations and over the validation start states."""
    per = [{"demo": d.meta.get("demo"), "split": d.meta.get("split"), "steps": d.steps, **reconstruction_error(d, t)}
           for d, t in zip(seen, truth, strict=True)]

    def mean(split: str, key: str) -> float:
        vals = [p[key] for p in per if (p["split"] == "train") == (split == "train") and np.isfinite(p[key])]
        return float(np.mean(vals)) if vals else float("nan")

    summary = {s: {k: mean(s, k) for k in ("hand_m", "object_m", "hand_reported", "object_reported")}
               for s in ("train", "validation_start")}
    path.write_text(json.dumps({"options": options.__dict__, "summary": summary, "demos": per}, indent=2))


def in_table_order(results: dict) -> dict:
    """The rows in Table 7.1's order, whatever order they were run in."""
    return {k: results[k] for k in sorted(results, key=lambda k: METHODS.index(k) if k in METHODS else 99)}


def write_tables(out: Path, results: dict, timing: dict, seed: int, quick: bool, n_train: int, n_val: int,
                 draw: int = 0, changes: dict | None = None, observed: str = "truth", task: str = "assembly") -> None:
    """results.json, results.md and results.png of one run."""
    (out / "results.json").write_text(json.dumps(results, indent=2))
    (out / "results.md").write_text(table(results, timing, seed=seed, quick=quick, n_train=n_train, n_val=n_val,
                                          draw=draw, changes=changes, observed=observed, task=task))
    plot_results(results, out / "results.png", ROWS)


def save_rollouts(outs: list[tuple[np.ndarray, np.ndarray]], path: Path, seed: int, quick: bool) -> None:
    """Every validation rollout of one method: hands_<i>, objects_<i> in validation order, and the
    protocol's seed and budget."""
    arrays = {"seed": np.array(seed), "quick": np.array(quick)}
    for i, (hands, objects) in enumerate(outs):
        arrays[f"hands_{i}"], arrays[f"objects_{i}"] = hands, objects
    np.savez_compressed(path, **arrays)


def rescore(out_dir: str | Path, seed: int = 0, demos: list[Demo] | None = None) -> dict[str, dict[str, float]]:
    """Scores recomputed from the saved rollouts of an earlier run in ``out_dir`` (same seed), with
    the metric as it is now; rewrites results.json, results.md and results.png."""
    out = Path(out_dir)
    files = sorted(out.glob("rollouts_*.npz"))
    if not files:
        raise EvaluationError(f"no rollouts_<method>.npz in {out}: run `xm eval --out {out}` first")
    if demos is None:
        demos = assembly_protocol(seed)
    train, val = split(demos)
    results, quick = {}, False
    for f in files:
        name = f.stem.removeprefix("rollouts_")
        try:
            with np.load(f) as z:
                saved_seed = int(z["seed"])
                if saved_seed == seed:
                    quick = quick or bool(z["quick"])
                    outs = [(z[f"hands_{i}"], z[f"objects_{i}"]) for i in range(len(val))]
        except (OSError, ValueError, KeyError, zipfile.BadZipFile) as exc:
            raise EvaluationError(f"{f} is unreadable or incomplete ({exc}): run that method again") from exc
        if saved_seed != seed:
            raise EvaluationError(f"{f} holds rollouts of seed {saved_seed}, not {seed}: give --seed {saved_seed}")
        results[name] = score(outs, val)
    results = in_table_order(results)
    timing = json.loads((out / "timing.json").read_text()) if (out / "timing.json").exists() else {}
    write_tables(out, results, timing, seed, quick, len(train), len(val))
    return results


def _fmt(x: float) -> str:
    return "inf" if not np.isfinite(x) else (f"{x:.4f}" if x < 0.1 else f"{x:.3f}")


def table(results: dict, timing: dict | None = None, seed: int = 0, quick: bool = False, n_train: int = 3,
          n_val: int = 12, draw: int = 0, changes: dict | None = None, observed: str = "truth",
          task: str = "assembly") -> str:
    """Markdown in the layout of Table 7.1, each cell with its ratio to the reference method."""
    ref = results.get(REFERENCE)
    lines = [f"Table 7.1 protocol, simulated {task}, seed {seed}"
             + (f", training draw {draw}" if draw else "")
             + (", rows (1)-(4) with " + ", ".join(f"{k}={v}" for k, v in changes.items()) if changes else "")
             + f": {n_train} train / {n_val} validation demos"
             + (f", observed {observed}" if observed != "truth" else "")
             + (" (--quick: tiny training budgets, numbers meaningless)" if quick else ""),
             "", "Symmetric closest-point distance in metres (lower is better); (x) = ratio to (1) Multimodal.", "",
             "| Method | Tactile | Memory | Hand | Object | Hand (masked) | Object (masked) | fit s | rollout s |",
             "|---|---|---|---|---|---|---|---|---|"]
    for name, r in results.items():
        label, tactile, memory = ROWS.get(name, (name, "?", "?"))
        cells = []
        for k in SCORE_KEYS:
            ratio = f" ({r[k] / ref[k]:.2f}x)" if ref and name != REFERENCE and ref[k] > 0 and np.isfinite(r[k]) else ""
            cells.append(_fmt(r[k]) + ratio)
        t = (timing or {}).get(name, {})
        lines.append(f"| {label} | {tactile} | {memory} | " + " | ".join(cells)
                     + f" | {t.get('fit_s', float('nan')):.1f} | {t.get('rollout_s', float('nan')):.1f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="xm eval", description="Table 7.1 protocol: fit every method on the task's training demonstrations "
        "(assembly: 3), roll out from its validation start states (assembly: 12), score with the symmetric "
        "closest-point distance. Writes results.json, "
        "results.md, results.png, rollout_<method>.png and, for rows (1)-(4), the scored net policy_<method>.pt "
        "into --out.")
    parser.add_argument("--task", default="assembly", choices=list(TASKS),
                        help="demonstrated task: " + "; ".join(f"{t.name} ({t.train} train / {t.validation} "
                                                               f"validation demos)" for t in TASKS.values())
                        + " (default %(default)s; docs/tasks.md)")
    parser.add_argument("--seed", type=int, default=0,
                        help="teacher layout seed of the task's demos (default %(default)s)")
    parser.add_argument("--seeds", default="",
                        help="comma-separated seeds: one run per seed and draw (--draws) into --out/seed<S>-draw<D>, "
                        "then summary.md/summary.json in --out: mean and spread per row, paired ratios to ours")
    parser.add_argument("--draws", type=int, default=1, help="with --seeds: training draws 0..N-1 per seed")
    parser.add_argument("--out", default="runs/eval", help="output directory (default %(default)s)")
    parser.add_argument("--methods", default=",".join(METHODS),
                        help="comma-separated subset of: " + ", ".join(METHODS) + " (default: all)")
    parser.add_argument("--draw", type=int, default=0,
                        help="training draw: the learned methods start from other random numbers (initial weights, "
                        "batches, noise), the demonstrations stay; one training run is one draw (default %(default)s)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="change a recipe field (ModelConfig, TrainConfig or InferenceConfig) of rows (1)-(4), "
                        "e.g. --set reservoir_periods=0.25,8 (repeatable)")
    parser.add_argument("--observations", default="truth", choices=OBSERVATIONS,
                        help="what the methods observe: the teacher's truth, or the demonstrations as recon "
                        "reconstructs them from rendered camera images (training demonstrations and validation start "
                        "states; scored against the truth either way; docs/policy.md) (default %(default)s)")
    parser.add_argument("--detector", default="learned", choices=DETECTORS,
                        help="--observations reconstructed: recon's 2-D detector; simulated projects the truth with "
                        "noise, dropouts and occlusion (no images) (default %(default)s)")
    parser.add_argument("--detector-weights", default=ReconOptions.weights,
                        help="--detector learned: the trained detector's folder (default %(default)s)")
    parser.add_argument("--recon-windows", default="roi", choices=WINDOWS,
                        help="--observations reconstructed: each camera reads camhub's window around the last "
                        "reconstructed hands (roi), or whole frames (default %(default)s)")
    parser.add_argument("--recon-cache", default="runs/recon_demos",
                        help="--observations reconstructed: folder caching reconstructed demonstrations per seed "
                        "and detector (default %(default)s)")
    parser.add_argument("--quick", action="store_true", help="tiny training budgets: a smoke test, not results")
    parser.add_argument("--merge", action="store_true",
                        help="keep the rows of other methods from an earlier run in --out in the table; refused "
                        "unless it is the same experiment (seed, draw, task, budget, observations, --set, the code "
                        "version of every kept row)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")
    parser.add_argument("--rescore", action="store_true",
                        help="no fitting: recompute the scores of an earlier run in --out from its saved rollouts")
    parser.add_argument("--execute", action="store_true",
                        help="robot in the loop instead: the trained policy (--checkpoint, a net of --task) drives the "
                        "simulated robot through trajopt and the control board on the task's validation layouts of "
                        "--seed and of --held-out-seeds, alone and with contact anchors (--variants); writes "
                        "execute.json and execute.md (tasks: assembly, latch, pick_place, wiping)")
    parser.add_argument("--checkpoint", default="runs/policy/policy.pt",
                        help="--execute: policy checkpoint (default %(default)s; `make policy` trains it)")
    parser.add_argument("--hand-feedback", action=argparse.BooleanOptionalAction, default=True,
                        help="--execute: the policy observes its grasping hand where the robot's gripper is (moved "
                             "rigidly onto the pads), as the thesis's robot saw its end-effector keypoints; "
                             "--no-hand-feedback: its own prediction (default: on)")
    parser.add_argument("--catch-mm", type=float, default=30.0,
                        help="--execute: hand feedback starts only once the gripper has come this close to the "
                        "policy's own hand (the gripper starts where no demonstrated hand was; docs/policy.md, "
                        "Robot in the loop); 0: from the first step (default %(default)s)")
    parser.add_argument("--anchors", action=argparse.BooleanOptionalAction, default=True,
                        help="--execute: contact anchors mined from the training demonstrations (grasp point and "
                        "heading, connector mate, pressures; docs/policy.md) close the last centimetres; "
                        "--no-anchors: the policy's goals as they are (default: on)")
    parser.add_argument("--layouts", type=int, default=12,
                        help="--execute: how many validation layouts per seed (default 12, at most the task's)")
    parser.add_argument("--held-out-seeds", default="",
                        help="--execute: comma-separated seeds whose validation layouts are run too, with the net and "
                        "the anchors of --seed (layouts never used to choose the loop's constants)")
    parser.add_argument("--variants", default=",".join(VARIANTS),
                        help="--execute: learned (the policy alone, no anchors), anchored (with contact anchors) or "
                        "both (default %(default)s)")
    parser.add_argument("--teacher", action="store_true",
                        help="--execute: the teacher's own hands instead of a policy (what the cell does with a "
                        "perfect policy)")
    args = parser.parse_args(argv)
    if args.set and (args.execute or args.rescore):
        print("error: --set changes the training of rows (1)-(4); --execute runs the checkpoint with its own config "
              "and --rescore trains nothing (drop --set, or train first: xm eval --set ... or xm train --set ...)",
              file=sys.stderr)
        return 2
    if args.execute:
        if args.catch_mm < 0 or not np.isfinite(args.catch_mm):
            print(f"error: --catch-mm must be 0 or a positive distance in mm, not {args.catch_mm}", file=sys.stderr)
            return 2
        return execute_main(args)
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    try:
        changes = config_changes(args.set)
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    try:
        recon = None
        if args.observations == "reconstructed":
            recon = ReconOptions(detector=args.detector, weights=args.detector_weights, windows=args.recon_windows)
        if args.rescore:
            rescore(args.out, args.seed, demos=task_spec(args.task).protocol(args.seed))
        elif args.seeds:
            try:
                seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
            except ValueError:
                raise EvaluationError(f"--seeds {args.seeds!r}: expected comma-separated integers") from None
            print(run_grid(lambda seed, draw, out: evaluate(
                args.task, seed, methods, out, quick=args.quick, progress=not args.no_progress, merge=args.merge,
                draw=draw, changes=changes, recon=recon, recon_cache=args.recon_cache), seeds, args.draws,
                Path(args.out), ROWS))
            return 0
        else:
            evaluate(args.task, args.seed, methods, args.out, quick=args.quick, progress=not args.no_progress,
                     merge=args.merge, draw=args.draw, changes=changes, recon=recon, recon_cache=args.recon_cache)
    except (EvaluationError, ReconstructionError, RunError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print((Path(args.out) / "results.md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
