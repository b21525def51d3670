"""Pictures of the skin tools' results (matplotlib, no display needed)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402 - after choosing the file-only backend
import numpy as np  # noqa: E402
from matplotlib.tri import Triangulation  # noqa: E402
from shapely import MultiPolygon, Polygon  # noqa: E402
from shapely.geometry.base import BaseGeometry  # noqa: E402

from skin.unwrap import face_edge_distortion  # noqa: E402


def distortion_png(path: str | Path, parts: list[tuple[str, np.ndarray, np.ndarray, dict[str, np.ndarray]]],
                   vmax: float | None = None) -> None:
    """Side by side per part, one column per method: the flat layout coloured by each face's edge
    distortion (|flat / surface length - 1|, mean of its edges), one colour scale for all.
    ``parts``: (name, surface vertices, faces, {method: uv})."""
    methods = list(parts[0][3])
    vals = [[face_edge_distortion(v, uv[m], f) for m in methods] for _, v, f, uv in parts]
    vmax = vmax or float(np.percentile(np.concatenate([x for row in vals for x in row]), 99))
    size = (3.8 * len(methods) + 1, 2.6 * len(parts))
    fig, axes = plt.subplots(len(parts), len(methods), figsize=size, squeeze=False)
    for row, ((name, _, f, uv), vs) in enumerate(zip(parts, vals, strict=True)):
        for col, (m, val) in enumerate(zip(methods, vs, strict=True)):
            ax = axes[row, col]
            tpc = ax.tripcolor(Triangulation(uv[m][:, 0], uv[m][:, 1], f), facecolors=val, cmap="inferno",
                               vmin=0, vmax=vmax)
            ax.set_aspect("equal")
            ax.set_title(f"{name}, {m}\nmean {val.mean():.4f}", fontsize=8)
            ax.tick_params(labelsize=6)
    fig.colorbar(tpc, ax=axes, label="edge-length distortion", shrink=0.6)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def unwrap_loss_png(path: str | Path, losses: dict[str, list[float]]) -> None:
    """The unwrap's loss (mean squared relative edge error) against iteration, per part."""
    fig, ax = plt.subplots(figsize=(5, 3))
    for name, loss in losses.items():
        ax.semilogy(loss, label=name, lw=1)
    ax.set_xlabel("iteration (noise rounds, then least-squares evaluations)")
    ax.set_ylabel("mean squared edge error")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def nesting_loss_png(path: str | Path, runs: list[list[tuple[float, float]]], baseline: float) -> None:
    """Simulated annealing's bounding-rectangle area against iteration (current and best, every
    seed) beside the bottom-left-fill baseline's best."""
    fig, ax = plt.subplots(figsize=(5.5, 3.2))
    for k, loss in enumerate(runs):
        arr = np.asarray(loss) / 100.0
        ax.plot(arr[:, 0], color="0.75", lw=0.5, label="current" if k == 0 else None)
        ax.plot(arr[:, 1], color="C0", lw=1, label="best so far" if k == 0 else None)
    ax.axhline(baseline / 100.0, color="C3", ls="--", label="bottom-left fill, best of the seeds")
    ax.set_xlabel("iteration")
    ax.set_ylabel("bounding rectangle (cm$^2$)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _draw(ax: plt.Axes, shape: BaseGeometry, **kw: object) -> None:
    polys = list(shape.geoms) if isinstance(shape, MultiPolygon) else [shape] if isinstance(shape, Polygon) else []
    for p in polys:
        ax.fill(*p.exterior.xy, **kw)
        for r in p.interiors:
            ax.fill(*r.xy, color="white")


def layout_png(path: str | Path, panels: dict[str, list[BaseGeometry]]) -> None:
    """Nested layouts side by side (one panel per layer or method)."""
    fig, axes = plt.subplots(1, len(panels), figsize=(4 * len(panels), 4), squeeze=False)
    for ax, (title, shapes) in zip(axes[0], panels.items(), strict=True):
        for k, g in enumerate(shapes):
            _draw(ax, g, color=plt.cm.tab20(k % 20), alpha=0.85)
        ax.set_aspect("equal")
        ax.set_title(title, fontsize=8)
        ax.tick_params(labelsize=6)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def layout_3d_png(path: str | Path, base_vertices: np.ndarray, base_faces: np.ndarray,
                  patches: list[tuple[str, np.ndarray, np.ndarray]], cells: np.ndarray,
                  view: tuple[float, float]) -> None:
    """The base mesh (grey), every sensor's patch (coloured) and its cell centres (black dots)."""
    fig = plt.figure(figsize=(6, 5))
    ax = fig.add_subplot(projection="3d")
    ax.plot_trisurf(*base_vertices.T, triangles=base_faces, color="0.85", alpha=0.25, lw=0)
    for k, (_, v, f) in enumerate(patches):
        ax.plot_trisurf(*v.T, triangles=f, color=plt.cm.tab10(k % 10), alpha=0.9, lw=0)
    ax.scatter(*cells.T, s=4, color="k", depthshade=False)
    lo, hi = base_vertices.min(axis=0), base_vertices.max(axis=0)
    c, r = (lo + hi) / 2, (hi - lo).max() / 2
    ax.set_xlim(c[0] - r, c[0] + r)
    ax.set_ylim(c[1] - r, c[1] + r)
    ax.set_zlim(c[2] - r, c[2] + r)
    ax.view_init(*view)
    ax.set_axis_off()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
