"""The plots of `xm eval`: the grouped bars of one run's table and one example rollout per method."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from learning.metrics import SCORE_KEYS
from shared.demo import Demo


def _pyplot():
    import matplotlib  # optional heavy dependency, loaded only to draw the plots

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_results(results: dict, path: Path, labels: dict[str, tuple[str, ...]]) -> None:
    plt = _pyplot()
    names = list(results)
    fig, ax = plt.subplots(figsize=(max(6, 1.1 * len(names) + 2), 4.5))
    x = np.arange(len(names))
    for i, key in enumerate(SCORE_KEYS):
        vals = [results[n][key] if np.isfinite(results[n][key]) else np.nan for n in names]
        ax.bar(x + (i - 1.5) * 0.2, vals, 0.2, label=key.replace("_", " "))
    ax.set_xticks(x, [labels.get(n, (n,))[0] for n in names], rotation=30, ha="right")
    ax.set_yscale("log")
    ax.set_ylabel("closest-point distance (m)")
    ax.set_title("Table 7.1 protocol (simulated assembly), lower is better")
    ax.grid(axis="y", which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_rollout(name: str, out: tuple[np.ndarray, np.ndarray], demo: Demo, path: Path, label: str) -> None:
    """Top view and height over time of the grasping hand's index tip and of the objects."""
    plt = _pyplot()
    hands, objects = out
    g = 1 if demo.meta.get("grasp_hand") == "right" else 0
    t_pred, t_ref = np.arange(len(hands)) * demo.dt, np.arange(demo.steps) * demo.dt
    fig, (top, side) = plt.subplots(1, 2, figsize=(11, 4.5))
    top.plot(demo.hands[:, g, 8, 0], demo.hands[:, g, 8, 1], "k--", lw=1.5, label="validation demo (index tip)")
    top.plot(hands[:, g, 8, 0], hands[:, g, 8, 1], "tab:red", lw=1.2, label=f"{name} (index tip)")
    top.plot(demo.objects[:, :, 0], demo.objects[:, :, 1], ".", color="0.6", ms=1)
    top.plot(objects[:, :, 0], objects[:, :, 1], ".", color="tab:green", ms=1)
    top.set_xlabel("x (m)")
    top.set_ylabel("y (m)")
    top.axis("equal")
    top.legend(fontsize=7)
    top.set_title("top view (objects: grey demo, green rollout)")
    side.plot(t_ref, demo.hands[:, g, 8, 2], "k--", lw=1.5, label="demo index tip")
    side.plot(t_pred, hands[:, g, 8, 2], "tab:red", lw=1.2, label="rollout index tip")
    side.plot(t_ref, demo.objects[:, 0, 2], ":", color="0.4", label=f"demo {demo.object_names[0]}")
    side.plot(t_pred, objects[:, 0, 2], color="tab:green", label=f"rollout {demo.object_names[0]}")
    side.set_xlabel("time (s)")
    side.set_ylabel("height (m)")
    side.legend(fontsize=7)
    side.set_title(f"{label}: validation demo {demo.meta.get('demo', 0)}")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
