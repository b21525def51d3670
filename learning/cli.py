"""The offline commands of the policy: `xm train` (train from recordings or teacher demonstrations)
and `xm simulate` (neural simulation of a trained policy from a teacher layout)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

from learning.dataset import DatasetError, demos_from_mcap, split_demos
from learning.from_library import library_data
from learning.metrics import trajectory_scores
from learning.ours import train
from learning.presets import PRESETS, config_changes
from learning.train import save_demos
from services.policy.model import Policy, PolicyError
from services.policy.runner import PolicyInputError, simulate
from services.world.teacher import assembly_protocol, generate_demo


def train_main(argv: list[str] | None = None) -> int:
    """`xm train`."""
    parser = argparse.ArgumentParser(prog="xm train", description="Train the denoising keypoint policy of thesis "
                                     "chapter 7; writes policy.pt (torch.load(weights_only=True)), config.json, "
                                     "train.json, loss.png and the training demonstrations (demos/).")
    parser.add_argument("recordings", nargs="*", help="MCAP recordings (scene + session keys), or one recordings "
                        "directory: the demonstration library, whose NAME.demo.json sidecars say which recordings "
                        "train, which validate and which are excluded, and trim them")
    parser.add_argument("--teacher", type=int, default=None, metavar="SEED",
                        help="instead: the 15-demonstration assembly protocol of this seed (3 train, 12 validation)")
    parser.add_argument("--preset", default="multimodal", choices=sorted(PRESETS))
    parser.add_argument("--steps", type=int, default=None, help="optimizer steps (default: the preset's)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="change a field of the preset's ModelConfig, TrainConfig or InferenceConfig, e.g. "
                        "--set reservoir_periods=0.25,8 (repeatable)")
    parser.add_argument("--val", type=int, default=0, help="recordings: hold out this many demonstrations")
    parser.add_argument("--threads", type=int, default=2,
                        help="torch threads (default %(default)s); 1 trains bit for bit as `xm eval` does, so "
                        "--teacher S --threads 1 gives the net of its row (1) (the thread count changes the "
                        "summation order, and with it the net)")
    parser.add_argument("--select", choices=["final", "validation"], default=None,
                        help="which weights are kept: the best on the held-out demonstrations' rollouts, or the "
                        "final (averaged) ones (default: validation where any is held out, except with --teacher: "
                        "final, as `xm eval` does, so the validation layouts stay unseen)")
    parser.add_argument("--out", default="runs/policy", help="output directory")
    parser.add_argument("--progress", default=None, metavar="FILE",
                        help="append the progress as JSON lines: {step, steps, loss} and {step, steps, eval}")
    args = parser.parse_args(argv)
    try:
        changes = config_changes(args.set)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2

    used: list[dict] = []
    if len(args.recordings) == 1 and Path(args.recordings[0]).is_dir():
        if args.val:
            print("error: --val with a recordings directory: the library's splits say which recordings validate",
                  file=sys.stderr)
            return 2
        data = library_data(args.recordings[0])
        for line in data.report:
            print(f"warning: {line}", file=sys.stderr)
        train_d, val_d, used = data.train, data.validation, data.used
        if not train_d:
            print(f"error: no training demonstrations in the library {args.recordings[0]} ({len(val_d)} for "
                  f"validation): mark recordings as train", file=sys.stderr)
            return 2
    elif args.recordings:
        demos = []
        for rec in args.recordings:
            report: list[str] = []
            try:
                demos += demos_from_mcap(rec, report=report)
            except DatasetError as exc:
                print(f"error: {exc}", file=sys.stderr)
                return 2
            for line in report:
                print(f"warning: {line}", file=sys.stderr)
        train_d, val_d = (demos[:-args.val], demos[-args.val:]) if args.val else (demos, [])
    elif args.teacher is not None:
        train_d, val_d = split_demos(assembly_protocol(args.teacher))
    else:
        print("error: no demonstrations: give recordings or --teacher SEED", file=sys.stderr)
        return 2
    if not train_d:
        print("error: no training demonstrations left", file=sys.stderr)
        return 2
    torch.set_num_threads(max(1, args.threads))
    cfg = PRESETS[args.preset].replace(**changes)
    if args.steps:
        cfg = cfg.replace(steps=args.steps)
    select = args.select or ("final" if args.teacher is not None and not args.recordings else "validation")
    held_out = val_d if select == "validation" and val_d else None  # None: the final weights are kept
    progress = _progress_writer(args.progress) if args.progress else None
    # the demonstrations first: a policy node waiting for this checkpoint replays them meanwhile
    save_demos(Path(args.out) / "demos", train_d)
    res = train(cfg, train_d, held_out, args.out, on_progress=progress)
    if used:  # the library's recordings behind this checkpoint, for the model list
        info_path = Path(args.out) / "train.json"
        info = json.loads(info_path.read_text())
        info.update(recordings=str(Path(args.recordings[0]).resolve()), data=used)
        info_path.write_text(json.dumps(info, indent=2))
    kept = f"best at step {res.best_step}" if held_out else "final weights"
    print(f"wrote {res.checkpoint} ({len(train_d)} train demonstrations, {kept} after {res.seconds_to_best:.0f} s "
          f"of {res.seconds:.0f} s; rollout distance {res.best_score * 1e3:.1f} mm from the "
          f"{'validation' if held_out else 'training'} start states)")
    return 0


def _progress_writer(path: str):
    """A callback appending each progress record as a JSON line, flushed (another process tails it)."""
    f = open(path, "a", buffering=1)  # noqa: SIM115 (open for the whole training; closed at exit)

    def write(record: dict) -> None:
        f.write(json.dumps(record) + "\n")

    return write


def simulate_main(argv: list[str] | None = None) -> int:
    """`xm simulate`."""
    parser = argparse.ArgumentParser(prog="xm simulate", description="Neural simulation of a trained policy from "
                                     "the start state of a teacher demonstration; writes rollout.npz and rollout.png.")
    parser.add_argument("checkpoint", help="policy.pt written by xm train")
    parser.add_argument("--seed", type=int, default=1234, help="layout seed of the start state")
    parser.add_argument("--seconds", type=float, default=8.0)
    parser.add_argument("--out", default="runs/simulate")
    args = parser.parse_args(argv)
    if not Path(args.checkpoint).exists():
        print(f"error: {args.checkpoint} not found (train one with `xm train --teacher 0`)", file=sys.stderr)
        return 2
    torch.set_num_threads(2)
    try:
        model = Policy.load(args.checkpoint)
    except (PolicyError, OSError, RuntimeError, KeyError, ValueError) as exc:
        print(f"error: cannot load {args.checkpoint}: {exc}", file=sys.stderr)
        return 2
    start = generate_demo("assembly", args.seed)
    steps = int(round(args.seconds / model.dt))
    try:
        roll = simulate(model, start, steps)
    except (PolicyError, PolicyInputError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(out / "rollout.npz", hands=roll.hands, objects=roll.objects, tactile=roll.tactile,
                        memory=roll.memory, object_names=np.array(start.object_names))
    scores = trajectory_scores(roll.hands, roll.objects, start)
    plot_rollout(roll, start, scores, out / "rollout.png")
    print(f"wrote {out / 'rollout.npz'} and {out / 'rollout.png'}; distance to the teacher: "
          f"hand {scores['hand'] * 1e3:.1f} mm, object {scores['object'] * 1e3:.1f} mm")
    return 0


def plot_rollout(roll, start, scores: dict, path: Path) -> None:
    """Top view of both index tips (rollout and teacher) and of the object points."""
    import matplotlib  # optional heavy dependency, loaded only to draw the plot

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 6))
    for h, color in ((0, "tab:red"), (1, "tab:blue")):
        ax.plot(roll.hands[:, h, 8, 0], roll.hands[:, h, 8, 1], color=color, label=f"{('left', 'right')[h]} index")
        ax.plot(start.hands[:, h, 8, 0], start.hands[:, h, 8, 1], "--", color=color, alpha=0.5, label="teacher")
    ax.plot(roll.objects[:, :, 0], roll.objects[:, :, 1], "g.", ms=1)
    ax.axis("equal")
    ax.legend(fontsize=7)
    ax.set_title(f"neural simulation: hand {scores['hand'] * 1e3:.1f} mm, object {scores['object'] * 1e3:.1f} mm")
    fig.savefig(path, dpi=110)
    plt.close(fig)
