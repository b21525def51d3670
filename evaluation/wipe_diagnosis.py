"""Where a wiping rollout goes wrong: `python -m evaluation.wipe_diagnosis RUN_DIR [--seed S]`.

For every saved rollout of an `xm eval --task wiping` run (rollouts_<method>.npz) and for the
teacher's validation demonstrations: how many steps the pad's face is within 5 mm of the plate
(what force control closes), and over the 4 s after the pad first comes over the plate within
3 cm of it: its median height above the plate's surface, its median distance from the marked
area's centre, its mean offset along and across the area and the spread across (the circles'
width). Pure numpy on saved rollouts; no training.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from services.world import wiping
from services.world.tasks import task
from services.world.teacher import object_names

WINDOW_STEPS = 200  # 4 s at 0.02 s: the teacher's wipe lasts 4.5-5 s
NEAR_M, ABOVE_M = 0.005, 0.03


def path_stats(objects: np.ndarray, names: list[str]) -> dict:
    """The figures above for one trajectory (T,K,3); NaN where the pad never comes over the plate."""
    comp = wiping.compression(objects, names)
    pad, centre = objects[:, names.index("sponge/bottom")], objects[:, names.index("plate/center")]
    height = pad[:, 2] - centre[:, 2]
    out = {"near_steps": int((comp >= -NEAR_M).sum())}
    low = np.flatnonzero(np.isfinite(comp) & (height < ABOVE_M))
    if not len(low):
        return out | {k: float("nan") for k in ("height_mm", "from_centre_mm", "along_mm", "across_mm",
                                                "across_sd_mm")}
    w = slice(low[0], low[0] + WINDOW_STEPS)
    a0, a1, a3 = (objects[w, names.index(f"plate/a{k}")] for k in (0, 1, 3))
    ex = (a1 - a0) / np.linalg.norm(a1 - a0, axis=-1, keepdims=True)
    ey = (a3 - a0) / np.linalg.norm(a3 - a0, axis=-1, keepdims=True)
    rel = pad[w] - centre[w]
    u, v = (rel * ex).sum(-1), (rel * ey).sum(-1)
    return out | {"height_mm": float(np.median(height[w]) * 1e3),
                  "from_centre_mm": float(np.median(np.linalg.norm(rel[:, :2], axis=-1)) * 1e3),
                  "along_mm": float(u.mean() * 1e3), "across_mm": float(v.mean() * 1e3),
                  "across_sd_mm": float(v.std() * 1e3)}


def report(rows: list[dict], label: str) -> str:
    lines = [f"{label}", "| # | steps within 5 mm | height mm | from centre mm | along mm | across mm | across sd mm |",
             "|---|---|---|---|---|---|---|"]
    for i, r in enumerate(rows):
        lines.append(f"| {i} | {r['near_steps']} | " + " | ".join(
            f"{r[k]:.1f}" for k in ("height_mm", "from_centre_mm", "along_mm", "across_mm", "across_sd_mm")) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m evaluation.wipe_diagnosis", description=__doc__.split("\n")[0])
    parser.add_argument("run", help="an `xm eval --task wiping` output folder")
    parser.add_argument("--seed", type=int, default=0, help="the run's seed (default %(default)s)")
    args = parser.parse_args(argv)
    names = object_names("wiping")
    files = sorted(Path(args.run).glob("rollouts_*.npz"))
    if not files:
        parser.error(f"no rollouts_<method>.npz in {args.run}")
    spec = task("wiping")
    val = spec.protocol(args.seed)[spec.train:]
    print(report([path_stats(d.objects, names) for d in val], f"teacher, seed {args.seed}"))
    for f in files:
        with np.load(f) as z:
            rows = [path_stats(z[f"objects_{i}"], names) for i in range(len(val))]
        print(report(rows, f.stem.removeprefix("rollouts_")))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
