"""The force-decided outcome of a task beside the Table 7.1 distances (`xm eval --task wiping|latch`).

Each validation rollout is judged by the world's success test (services/world/tasks.py). A method
that predicts touch is executed with that touch as force (force control, the robot mapping of
its task); any other method's force is what a position-controlled robot following its keypoints
would press with (services/world/wiping.py, latch.py say how the positions give a force).
"""

from __future__ import annotations

import numpy as np

from services.world.tasks import TASKS, outcome
from shared.demo import Demo


def predicted_touch(method, start: Demo, steps: int) -> np.ndarray | None:
    """(steps,2,R) kPa a method's neural simulation predicts from ``start``, or None where the method
    predicts no touch."""
    policy = getattr(method, "policy", None)
    if policy is None or not getattr(policy.cfg, "tactile", False):
        return None
    state = policy.initial_state(start)
    tact = policy.roll(state, steps - 1)[1]
    return np.concatenate([start.tactile[:1].astype(float), tact])


def task_measure(task: str, method, outs: list[tuple[np.ndarray, np.ndarray]], val: list[Demo],
                 starts: list[Demo] | None = None) -> dict | None:
    """{measure, force_source, mean, success_rate, rollouts} for a task whose success force decides;
    None for the others."""
    spec = TASKS[task]
    if spec.measure is None:
        return None
    starts = val if starts is None else starts
    per, source = [], "positions"
    for (hands, objects), start, demo in zip(outs, starts, val, strict=True):
        if not (np.isfinite(hands).all() and np.isfinite(objects).all()):
            per.append({spec.measure: 0.0, "success": False, "diverged": True})
            continue
        touch = predicted_touch(method, start, len(hands))
        source = "predicted touch" if touch is not None else source
        r = outcome(task, hands, objects, demo.object_names, touch)
        per.append({k: (float(v) if isinstance(v, (int, float, np.floating)) and not isinstance(v, bool) else v)
                    for k, v in r.items()})
    values = [float(p[spec.measure]) for p in per]
    return {"measure": spec.measure, "force_source": source, "mean": float(np.mean(values)),
            "spread": float(np.std(values)), "success_rate": float(np.mean([p["success"] for p in per])),
            "rollouts": per}


def measure_table(task: str, measures: dict, rows: dict[str, str] | None = None) -> str:
    """Markdown: the task's force-decided outcome per method, and row (1) against row (2)."""
    spec, rows = TASKS[task], rows or {}
    lines = ["", f"{task}: {spec.success}. Force from the method's predicted touch (force control) or, without "
             "touch, from its positions (position control).", "",
             f"| Method | force from | {spec.measure} (mean +- sd) | success |", "|---|---|---|---|"]
    for name, m in measures.items():
        lines.append(f"| {rows.get(name, name)} | {m['force_source']} | {m['mean']:.3f} +- {m['spread']:.3f} "
                     f"| {m['success_rate'] * 100:.0f} % |")
    if "multimodal" in measures and "no_tactile" in measures:
        a, b = measures["multimodal"]["mean"], measures["no_tactile"]["mean"]
        ratio = f"{a / b:.2f}x" if b > 0 else ("inf (row (2) scores 0)" if a > 0 else "none (both score 0)")
        lines += ["", f"(1) Multimodal against (2) No tactile on {spec.measure}: {ratio} (target >= 1.3x)"]
    return "\n".join(lines) + "\n"

