"""Policy benchmarks P4 (policy step and 1 s horizon) and P5 (training time to the best rollout).

P4: one policy step with the consistency solve, and a 1 s horizon rollout at the policy's sample
period and at the trajectory optimizer's knots, through the compiled loop the node runs, against
the torch reference step (evaluation/reference.py) measured in the same run. P5: training wall
time to the best validation rollout. Writes .bench/policy.json.
Timing is reported, never asserted.

    .venv/bin/python bench/policy.py            # P4 on a briefly trained model, P5 with the preset
    .venv/bin/python bench/policy.py --quick    # P5 with a short training (smoke)
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from evaluation.reference import network_outputs, reference_roll, reference_step  # noqa: E402
from learning.dataset import split_demos  # noqa: E402
from learning.ours import train  # noqa: E402
from learning.presets import preset  # noqa: E402
from services.policy.model import Policy  # noqa: E402
from services.policy.runner import PolicyRunner, SceneObs  # noqa: E402
from services.world.teacher import assembly_protocol  # noqa: E402
from shared.demo import Demo  # noqa: E402

KNOTS_1S = 20  # the trajectory optimizer's knots over its 1 s horizon (services/trajopt)


def median_ms(fn, n: int) -> float:
    for _ in range(5):
        fn()
    times = []
    for _ in range(n):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times) * 1e3)


def p4(model: Policy, d: Demo) -> dict:
    """One policy step and a 1 s horizon through the compiled loop (the node's one inference path),
    against the same on the torch network (evaluation/reference.py) in this process; one thread,
    as the service runs it. The state is one from inside the task, not the rest pose."""
    torch.set_num_threads(1)
    model.net.eval()
    state = model.initial_state(d)
    for _ in range(50):
        state = model.step(state)
    scene = SceneObs(d.hands[0].astype(float), d.hand_mask[0], d.objects[0].astype(float), d.object_mask[0],
                     d.tactile[0], d.tactile_mask[0])
    steps_1s = int(round(1.0 / model.dt))
    report = {"P4_masked_points_in_state": int((~state["mask"]).sum()), "P4_horizon_steps": steps_1s,
              "P4_horizon_knots": KNOTS_1S}
    report["P4_step_ms_p50"] = median_ms(lambda: model.step(state), 300)
    report["P4_step_ms_p50_reference"] = median_ms(lambda: reference_step(model, state), 100)
    report["P4_forward_only_ms_p50_reference"] = median_ms(lambda: network_outputs(model, state), 100)
    runner = PolicyRunner(model)
    runner.step(scene)
    report["P4_horizon_1s_ms_p50"] = median_ms(lambda: runner.horizon(None, steps_1s), 20)
    report["P4_horizon_1s_ms_p50_reference"] = median_ms(lambda: reference_roll(model, runner.state, steps_1s), 5)
    # as the cell rolls it out: at the trajectory optimizer's 20 knots (7.16's keyframes)
    report["P4_horizon_1s_knots_ms_p50"] = median_ms(lambda: runner.horizon(None, KNOTS_1S, 1.0 / KNOTS_1S), 20)
    report["P4_step_speedup_vs_reference"] = report["P4_step_ms_p50_reference"] / report["P4_step_ms_p50"]
    report["P4_horizon_1s_speedup_vs_reference"] = (report["P4_horizon_1s_ms_p50_reference"]
                                                    / report["P4_horizon_1s_ms_p50"])
    return report


def cpu_model() -> str:
    """The host's CPU as /proc/cpuinfo names it: the figures differ about 3x between hosts."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return "unknown"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="short training for P5")
    parser.add_argument("--preset", default="multimodal")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=".bench/policy.json")
    parser.add_argument("--checkpoint", help="P4 only, on this trained policy.pt (no training, P5 not measured)")
    parser.add_argument("--keep", metavar="DIR",
                        help="also write the P5 training's checkpoint, config and loss plot here")
    args = parser.parse_args()

    demos = assembly_protocol(args.seed)
    tr, va = split_demos(demos)
    report: dict = {}
    if args.checkpoint:
        model = Policy.load(args.checkpoint)
    else:  # P5: training to the best validation rollout (2 threads, the budget of the brief)
        torch.set_num_threads(2)
        cfg = preset(args.preset)
        if args.quick:
            cfg = cfg.replace(steps=200, eval_every=100)
        t0 = time.perf_counter()
        res = train(cfg, tr, va, args.keep, progress=False)
        total = time.perf_counter() - t0
        model = res.method.policy
        report |= {"P5_train_seconds_to_best": res.seconds_to_best, "P5_train_seconds_total": total,
                   "P5_best_step": res.best_step, "P5_steps": cfg.train.steps,
                   "P5_best_rollout_hand_m": min(e["hand"] for e in res.evals),
                   "P5_best_rollout_object_m": min(e["object"] for e in res.evals)}
    report |= p4(model, va[0])
    report |= {"preset": model.name, "threads": {"P4": 1, "P5": 2}, "quick": args.quick,
               "checkpoint": args.checkpoint, "cpu": cpu_model()}
    out_path = Path(args.out)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    out_path.write_text(json.dumps(report, indent=2))
    for k, val in report.items():
        print(f"{k}: {val:.3f}" if isinstance(val, float) else f"{k}: {val}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
