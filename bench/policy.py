"""Policy benchmarks: P4 (one policy step with the consistency solve; a 1 s horizon rollout) against
the plain forward pass measured in the same run, and P5 (training wall time to the best validation
rollout). Writes .bench/policy.json. Timing is reported, never asserted.

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


def median_ms(fn, n: int) -> float:
    for _ in range(5):
        fn()
    times = []
    for _ in range(n):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times) * 1e3)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="short training for P5")
    parser.add_argument("--preset", default="multimodal")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=".bench/policy.json")
    args = parser.parse_args()
    from services.policy.dataset import split_demos
    from services.policy.network import preset
    from services.policy.ours import Ours
    from services.policy.simulate import PolicyRunner, SceneObs
    from services.policy.train import train
    from services.world.teacher import assembly_protocol

    demos = assembly_protocol(args.seed)
    tr, va = split_demos(demos)
    # P5: training to the best validation rollout (2 threads, the budget of the brief)
    torch.set_num_threads(2)
    cfg = preset(args.preset)
    if args.quick:
        cfg = cfg.replace(steps=200, eval_every=100)
    t0 = time.perf_counter()
    res = train(cfg, tr, va, None, progress=False)
    total = time.perf_counter() - t0
    model: Ours = res.method
    # P4: one thread, as the service runs it
    torch.set_num_threads(1)
    model.net.eval()
    solver = model.solver()
    state = model.initial_state(va[0])
    for _ in range(50):  # a state from inside the task, not the rest pose
        state = model.step(state, solver)
    step_ms = median_ms(lambda: model.step(state, solver), 300)
    forward_ms = median_ms(lambda: model.network_outputs(state), 300)
    out = model.network_outputs(state)
    v = out["vel"].reshape(-1, 3) / 5.0
    solve_ms = median_ms(lambda: solver.positions(state["pos"], v, None), 300)
    runner = PolicyRunner(model)
    d = va[0]
    scene = SceneObs(d.hands[0].astype(float), d.hand_mask[0], d.objects[0].astype(float), d.object_mask[0],
                     d.tactile[0], d.tactile_mask[0])
    runner.step(scene)
    steps_1s = int(round(1.0 / model.dt))
    horizon_ms = median_ms(lambda: runner.horizon(None, steps_1s), 20)
    report = {
        "P4_step_ms_p50": step_ms, "P4_forward_only_ms_p50": forward_ms,
        "P4_solve_overhead_ratio": step_ms / forward_ms, "P4_integral_only_solve_ms_p50": solve_ms,
        "P4_horizon_1s_ms_p50": horizon_ms, "P4_horizon_steps": steps_1s,
        "P5_train_seconds_to_best": res.seconds_to_best, "P5_train_seconds_total": total,
        "P5_best_step": res.best_step, "P5_steps": cfg.steps,
        "P5_best_rollout_hand_m": min(e["hand"] for e in res.evals),
        "P5_best_rollout_object_m": min(e["object"] for e in res.evals),
        "preset": cfg.name, "threads": {"P4": 1, "P5": 2}, "quick": args.quick,
    }
    out_path = Path(args.out)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    out_path.write_text(json.dumps(report, indent=2))
    for k, val in report.items():
        print(f"{k}: {val:.3f}" if isinstance(val, float) else f"{k}: {val}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
