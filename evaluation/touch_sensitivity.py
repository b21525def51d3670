"""Can vision alone tell the force on a force-decided task? The task's success test on the
teacher's own validation demonstrations, with the pressing hand (and on wiping the sponge it
holds) moved up or down by a few millimetres, as a policy's height error would move them, and
the force taken either from the positions (what a position-controlled robot following them
presses with: rows without touch) or from the glove's force (force control: rows that predict
touch; the policy's own touch error is not modelled here).

    python -m evaluation.touch_sensitivity --task wiping --out docs/touch_sensitivity_wiping.json

No training: it tells whether the task leaves room for touch to matter, and how many millimetres
of height error a method without touch can afford (docs/tasks.md).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from services.world.tasks import TASKS, UnknownTaskError, outcome
from services.world.teacher import KPA_PER_N, Teacher
from shared.demo import Demo

OFFSETS_MM = (-3.0, -2.0, -1.0, -0.5, 0.0, 0.5, 1.0, 2.0, 3.0, 6.0, 10.0)
MOVED = {"wiping": ("sponge/",), "latch": ()}  # held objects that move with the pressing hand


def glove_force(demo: Demo) -> np.ndarray:
    """(T,2,R) kPa the teacher's hands really pressed with (both hands, as demo_outcome takes it)."""
    m = demo.meta
    teacher = Teacher(m["task"], m["seed"], m["grasp_hand"], m["tactile_hand"])
    return np.array([teacher.state(i * demo.dt).forces for i in range(demo.steps)]) * KPA_PER_N


def shifted(demo: Demo, task: str, dz_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Hands and objects with both hands and the held objects moved by ``dz_m`` vertically."""
    hands = demo.hands.astype(float).copy()
    objects = demo.objects.astype(float).copy()
    hands[..., 2] += dz_m
    held = [i for i, n in enumerate(demo.object_names) if n.startswith(MOVED[task])] if MOVED[task] else []
    objects[:, held, 2] += dz_m
    return hands, objects


def sensitivity(task: str, demos: list[Demo], offsets_mm: tuple[float, ...] = OFFSETS_MM) -> dict:
    """Per height offset: success rate and mean of the task's measure, force from positions and from
    the glove."""
    spec = TASKS[task]
    if spec.measure is None or task not in MOVED:
        raise UnknownTaskError(f"task {task!r} has no force-decided measure here; tasks: {', '.join(MOVED)}")
    forces = [glove_force(d) for d in demos]
    rows = []
    for off in offsets_mm:
        row = {"offset_mm": off}
        for source in ("positions", "glove"):
            res = [outcome(task, *shifted(d, task, off * 1e-3), d.object_names, f if source == "glove" else None)
                   for d, f in zip(demos, forces, strict=True)]
            row[source] = {"success_rate": float(np.mean([r["success"] for r in res])),
                           "measure": float(np.mean([float(r[spec.measure]) for r in res])),
                           "peak_force_n": float(np.mean([r["peak_force_n"] for r in res]))}
        rows.append(row)
    return {"task": task, "measure": spec.measure, "demonstrations": len(demos), "rows": rows}


def table(result: dict) -> str:
    m = result["measure"]
    lines = [f"| height offset (mm) | from positions: success, {m}, peak N | from the glove: success, {m}, peak N |",
             "|---|---|---|"]
    for r in result["rows"]:
        p, g = r["positions"], r["glove"]
        lines.append(f"| {r['offset_mm']:+.1f} | {p['success_rate'] * 100:.0f} %, {p['measure']:.2f}, "
                     f"{p['peak_force_n']:.1f} | {g['success_rate'] * 100:.0f} %, {g['measure']:.2f}, "
                     f"{g['peak_force_n']:.1f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--task", default="wiping", help=f"one of {', '.join(MOVED)}")
    parser.add_argument("--seed", type=int, default=0, help="teacher layout seed (default %(default)s)")
    parser.add_argument("--out", default="", help="write the result as JSON here")
    args = parser.parse_args(argv)
    if args.task not in MOVED:
        print(f"error: unknown task {args.task!r}; tasks with a force-decided measure: {', '.join(MOVED)}")
        return 2
    demos = [d for d in TASKS[args.task].protocol(args.seed) if d.meta.get("split") == "validation"]
    result = sensitivity(args.task, demos)
    print(table(result))
    if args.out:
        Path(args.out).write_text(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
