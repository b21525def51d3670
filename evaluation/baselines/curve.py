"""The validation curve of a baseline trained for many iterations (the Diffusion Policy rows):
the validation rollout scores against training iterations, as JSON and a plot."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np


def record(method, done: int, every: int, t0: float) -> float:
    """Append ``method.monitor(method)`` at iteration ``done`` to ``method.curve`` (with the mean
    loss of the last ``every`` iterations and the training time so far); returns ``t0`` moved on by
    the time the scoring took, so that ``train_s`` counts training only."""
    t_eval = time.perf_counter()
    method.curve.append({"iteration": done, "loss": float(np.mean(method.losses[-every:])),
                         "train_s": t_eval - t0, **method.monitor(method)})
    print(f"{method.name} {json.dumps(method.curve[-1])}", file=sys.stderr, flush=True)  # a long run's trace
    return t0 + time.perf_counter() - t_eval


def save_curve(name: str, config: dict, curve: list[dict], json_path: Path, png_path: Path) -> None:
    """The curve and the method's configuration as JSON, the distances against iterations as PNG."""
    Path(json_path).write_text(json.dumps({"method": name, "config": config, "curve": curve}, indent=2))
    import matplotlib  # optional heavy dependency, loaded only to draw the curve

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    it = [c["iteration"] for c in curve]
    fig, ax = plt.subplots(figsize=(6, 4))
    for key in ("hand", "object", "hand_masked", "object_masked"):
        ax.plot(it, [c[key] * 1e3 for c in curve], "o-", label=key.replace("_", " "))
    ax.set_xlabel("training iteration")
    ax.set_ylabel("validation closest-point distance (mm)")
    ax.set_yscale("log")
    ax.set_title(f"{name}: validation rollouts")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(png_path, dpi=100)
    plt.close(fig)
