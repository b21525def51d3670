"""The calibration report: per camera RMS reprojection error, detections, image coverage; in the
simulation also the error against the true cameras. JSON for tools, PNG for people."""

from __future__ import annotations

import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only, no display
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from calibration.detect import Detections  # noqa: E402
from calibration.pipeline import Calibrated  # noqa: E402
from shared.calibration import RigCalibration  # noqa: E402

COVERAGE_GRID = (16, 12)  # cells across, down


def coverage(uv: np.ndarray, size: tuple[int, int]) -> float:
    """Fraction of the image's grid cells holding at least one detected corner."""
    gx, gy = COVERAGE_GRID
    if len(uv) == 0:
        return 0.0
    cx = np.clip((uv[:, 0] / size[0] * gx).astype(int), 0, gx - 1)
    cy = np.clip((uv[:, 1] / size[1] * gy).astype(int), 0, gy - 1)
    return len(set(zip(cx.tolist(), cy.tolist(), strict=True))) / (gx * gy)


def rotation_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(Ra.T @ Rb) - 1) / 2, -1.0, 1.0))))


def truth_errors(rig: RigCalibration, truth: dict[str, tuple[np.ndarray, np.ndarray]]) -> dict[str, dict]:
    """Per camera: focal length %, principal point px, position mm, rotation degrees against
    ``truth[name] = (K, world_T_cam)`` in OpenCV conventions."""
    out = {}
    for cam in rig.cameras:
        if cam.name not in truth:
            continue
        K, T = truth[cam.name]
        out[cam.name] = {
            "focal_pct": float(100 * max(abs(cam.K[0, 0] / K[0, 0] - 1), abs(cam.K[1, 1] / K[1, 1] - 1))),
            "principal_point_px": float(np.linalg.norm(cam.K[:2, 2] - K[:2, 2])),
            "position_mm": float(1000 * np.linalg.norm(cam.world_T_cam[:3, 3] - T[:3, 3])),
            "rotation_deg": rotation_deg(cam.world_T_cam[:3, :3], T[:3, :3]),
        }
    return out


def build(cal: Calibrated, det: Detections, truth: dict | None = None, timing: dict | None = None) -> dict:
    b = cal.bundle
    cams = {}
    for c, name in enumerate(det.names):
        sel = b.obs.cam == c
        kept = sel & b.inlier
        cams[name] = {
            "rms_px": round(cal.rig.cameras[c].rms_px, 4),
            "views": int(len({int(f) for f in b.obs.frame[sel]})),
            "corners": int(kept.sum()),
            "outliers": int((sel & ~b.inlier).sum()),
            "skipped": det.skipped_by_camera()[name],
            "coverage": round(coverage(b.obs.uv[kept], det.image_sizes[c]), 3),
            "image_size": list(det.image_sizes[c]),
        }
    report = {"frame_sets": det.n_frames, "board": cal.rig.board, "cameras": cams,
              "seconds": {k: round(v, 3) for k, v in {**cal.seconds, **(timing or {})}.items()},
              "iterations": b.iterations}
    if truth:
        errs = truth_errors(cal.rig, truth)
        report["truth"] = {n: {k: round(v, 4) for k, v in e.items()} for n, e in errs.items()}
        report["truth_max"] = {k: round(max(e[k] for e in errs.values()), 4) for k in next(iter(errs.values()))}
    return report


def text(report: dict) -> str:
    lines = [f"{'camera':<8} {'rms px':>7} {'views':>6} {'corners':>8} {'outliers':>8} {'coverage':>8}  skipped"]
    for name, c in report["cameras"].items():
        skipped = ", ".join(f"{k} {v}" for k, v in sorted(c["skipped"].items())) or "-"
        lines.append(f"{name:<8} {c['rms_px']:>7.3f} {c['views']:>6} {c['corners']:>8} {c['outliers']:>8} "
                     f"{c['coverage']:>8.2f}  {skipped}")
    if "truth" in report:
        lines += ["", "against the simulator's true cameras:",
                  f"{'camera':<8} {'focal %':>8} {'pp px':>7} {'pos mm':>7} {'rot deg':>8}"]
        for name, e in {**report["truth"], "max": report["truth_max"]}.items():
            lines.append(f"{name:<8} {e['focal_pct']:>8.4f} {e['principal_point_px']:>7.3f} "
                         f"{e['position_mm']:>7.3f} {e['rotation_deg']:>8.4f}")
    lines.append("")
    lines.append("time: " + ", ".join(f"{k} {v:.2f}" for k, v in report["seconds"].items()))
    return "\n".join(lines)


def write(report: dict, cal: Calibrated, det: Detections, json_path: Path, png_path: Path) -> None:
    json_path.write_text(json.dumps(report, indent=1) + "\n")
    b = cal.bundle
    n = len(det.names)
    cols = min(n, 4)
    rows = (n + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(4 * cols, 3.2 * rows), squeeze=False)
    err = np.linalg.norm(b.residuals, axis=1)
    for c, name in enumerate(det.names):
        ax = axes[c // cols][c % cols]
        sel = b.obs.cam == c
        w, h = det.image_sizes[c]
        sc = ax.scatter(b.obs.uv[sel, 0], b.obs.uv[sel, 1], c=err[sel], s=2, cmap="viridis", vmin=0,
                        vmax=max(0.5, 3 * report["cameras"][name]["rms_px"]))
        out = sel & ~b.inlier
        ax.scatter(b.obs.uv[out, 0], b.obs.uv[out, 1], s=8, marker="x", color="red")
        ax.set_xlim(0, w)
        ax.set_ylim(h, 0)
        ax.set_aspect("equal")
        cam = report["cameras"][name]
        ax.set_title(f"{name}: {cam['rms_px']:.3f} px, {cam['views']} views, cov {cam['coverage']:.2f}", fontsize=8)
        ax.tick_params(labelsize=6)
        fig.colorbar(sc, ax=ax, fraction=0.04).ax.tick_params(labelsize=6)
    for k in range(n, rows * cols):
        axes[k // cols][k % cols].axis("off")
    fig.suptitle("detected corners, coloured by reprojection error (px); red x: rejected outliers", fontsize=9)
    fig.tight_layout()
    fig.savefig(png_path, dpi=90)
    plt.close(fig)
