"""Crosstalk compensation speed: one 16x16 frame, median over many, against the exact direct solve
(one 16x16 linear system per reception line) and the naive divider in the same run.
Writes .bench/crosstalk.json. Target: <= 1 ms per frame."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # runnable as a script from anywhere

from services.glove.crosstalk import compensate, direct, naive, readings  # noqa: E402


def median_us(fn, frames: list[np.ndarray]) -> float:
    times = []
    for v in frames:
        t0 = time.perf_counter()
        fn(v, 1e-3)
        times.append(time.perf_counter() - t0)
    return float(np.median(times) * 1e6)


def main() -> None:
    argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter).parse_args()
    rng = np.random.default_rng(1)
    frames = []
    for _ in range(2000):
        G = np.full((16, 16), 1e-6)
        r, c = rng.integers(0, 15, 2)
        G[r:r + 2, c:c + 2] = rng.uniform(1e-4, 1e-3)
        frames.append(readings(G, 1e-3))
    res = {"compensate_median_us": median_us(compensate, frames), "naive_median_us": median_us(naive, frames),
           "direct_solve_median_us": median_us(direct, frames[:300]),
           "plain_iteration_median_us": median_us(lambda v, g: compensate(v, g, closed_form_start=False), frames)}
    res["ratio_to_naive"] = res["compensate_median_us"] / res["naive_median_us"]
    res["speedup_vs_direct"] = res["direct_solve_median_us"] / res["compensate_median_us"]
    res["target_us_max"] = 1000.0
    Path(".bench").mkdir(exist_ok=True)
    Path(".bench/crosstalk.json").write_text(json.dumps(res, indent=2))
    print(f"compensation {res['compensate_median_us']:.1f} us/frame, direct solve "
          f"{res['direct_solve_median_us']:.1f} us ({res['speedup_vs_direct']:.1f}x faster; "
          f"naive divider {res['naive_median_us']:.1f} us, "
          f"{res['ratio_to_naive']:.1f}x; plain iteration from the naive start "
          f"{res['plain_iteration_median_us']:.0f} us); target <= 1000 us")


if __name__ == "__main__":
    main()
