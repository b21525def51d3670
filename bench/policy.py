"""P4 and P5: the chapter-7 policy's step time (including the consistency solve) and a 1 s horizon
rollout, against the bare network forward pass in the same run; training wall time on 3 teacher
demonstrations. Writes .bench/policy.json. Targets: step p50 <= 0.5 ms, 1 s rollout <= 10 ms,
training <= 10 min."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import torch

from services.policy.ours import PRESETS, Ours, PolicyConfig
from services.world.teacher import assembly_protocol


def median_ms(fn, n: int) -> float:
    times = []
    for _ in range(n):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times) * 1e3)


def main() -> None:
    torch.set_num_threads(1)
    demos = assembly_protocol(0)
    train = [d for d in demos if d.meta["split"] == "train"]
    cfg = PRESETS["multimodal"]
    method = Ours(PolicyConfig(**{**cfg.__dict__, "steps": 1500}))
    torch.set_num_threads(2)
    method.fit(train, progress=True)
    torch.set_num_threads(1)
    state = method.initial_state(demos[5])
    x = torch.zeros(1, method.net.mean.shape[0])

    def forward() -> None:
        with torch.no_grad():
            method.net(x)

    res = {"train_seconds_1500_steps": method.train_seconds,
           "forward_only_ms_p50": median_ms(forward, 500),
           "step_with_consistency_ms_p50": median_ms(lambda: method.step(state), 500),
           "rollout_1s_ms_p50": median_ms(lambda: method.rollout(demos[5], int(1.0 / method.dt)), 20)}
    res["step_overhead_ratio"] = res["step_with_consistency_ms_p50"] / res["forward_only_ms_p50"]
    res["targets"] = {"step_ms_p50_max": 0.5, "rollout_1s_ms_max": 10.0, "train_minutes_max": 10.0}
    Path(".bench").mkdir(exist_ok=True)
    Path(".bench/policy.json").write_text(json.dumps(res, indent=2))
    print(json.dumps(res, indent=2))


if __name__ == "__main__":
    main()
