"""Sensor-skin tools (thesis 4.5.4, 4.8.1) on the glove and fingertip examples: unwrap distortion
against LSCM, nesting against bottom-left fill, toolpath travel. Writes .bench/skin.json.

Unwrap: per part, the mean (and max) edge-length distortion |flat / surface length - 1| and the
face area range of the stretch-minimizing unwrap and of LSCM (libigl) scaled by its best factor,
flipped faces of each. Target: on the glove's five finger parts the mean at least 3x lower than
LSCM's, no flipped face.

Nesting: each glove layer (electrodes, dielectric) nested by simulated annealing and by
bottom-left fill (order and strip width drawn per seed), ``--seeds`` seeds each, on the same
pieces and margin; every layout's smallest gap checked exactly. Target: annealing's bounding
rectangle within 15 % of bottom-left fill's best (ratio <= 1.15), margin never violated.

Toolpaths: knife travel of the ordered SVG paths against cutting them in listed order.

``--docs`` also draws the pictures of docs/skin.md. Wall times are medians over the parts or
seeds, on whatever else the host runs (the load average is recorded).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

from skin import examples, plots
from skin.nest import anneal
from skin.pipeline import baseline, layers, marker, unwrap_parts
from skin.toolpath import contours, order, travel_in_given_order

ROOT = Path(__file__).resolve().parents[1]
FINGERS = ("thumb", "index", "middle", "ring", "little")


def unwrap_figures(design: examples.Design) -> tuple[list, dict]:
    t = time.perf_counter()
    parts = unwrap_parts(design)
    wall = (time.perf_counter() - t) / len(parts)
    out = {}
    keys = ("edge_mean", "edge_max", "area_min", "area_max", "flipped")
    for r in parts:
        o, lo = r.report["ours"], r.report["lscm"]
        out[r.placement.spec.name] = {
            "faces": o["faces"], "ours": {k: o[k] for k in keys}, "lscm": {k: lo[k] for k in keys},
            "mean_ratio_lscm_over_ours": lo["edge_mean"] / max(o["edge_mean"], 1e-12)}
    return parts, {"parts": out, "wall_s_per_part": wall}


def nesting_figures(pieces: list, margin: float, sheet: tuple[float, float], seeds: int, iterations: int
                    ) -> tuple[dict, list, list]:
    blf, sa, t_blf, t_sa = [], [], [], []
    for s in range(seeds):
        t = time.perf_counter()
        blf.append(baseline(pieces, margin, sheet, s))
        t_blf.append(time.perf_counter() - t)
        t = time.perf_counter()
        sa.append(anneal(pieces, margin, sheet, iterations, s))
        t_sa.append(time.perf_counter() - t)
    a_blf, a_sa = np.array([n.area for n in blf]), np.array([n.area for n in sa])
    fig = {"pieces": len(pieces), "parts_area_mm2": float(sum(p.shape.area for p in pieces)),
           "blf_area_mm2": a_blf.round(1).tolist(), "sa_area_mm2": a_sa.round(1).tolist(),
           "blf_best_mm2": float(a_blf.min()), "sa_best_mm2": float(a_sa.min()),
           "sa_median_mm2": float(np.median(a_sa)),
           "sa_worst_mm2": float(a_sa.max()),
           "ratio_sa_best_over_blf_best": float(a_sa.min() / a_blf.min()),
           "ratio_sa_median_over_blf_best": float(np.median(a_sa) / a_blf.min()),
           "ratio_sa_worst_over_blf_best": float(a_sa.max() / a_blf.min()),
           "min_gap_mm": float(min(n.min_gap for n in blf + sa)), "margin_mm": margin,
           "wall_s_median": {"blf": float(np.median(t_blf)), "sa": float(np.median(t_sa))}}
    return fig, blf, sa


def travel_figures(shapes: list) -> dict[str, float]:
    groups = [g for s in shapes for g in contours(s)]
    _, ordered = order(groups)
    return {"ordered_mm": ordered, "listed_order_mm": travel_in_given_order(groups)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--iterations", type=int, default=4000)
    ap.add_argument("--margin", type=float, default=2.0)
    ap.add_argument("--docs", action="store_true", help="draw docs/skin_*.png")
    args = ap.parse_args()
    sheet = (200.0, 300.0)
    out = {"load_average": os.getloadavg()[0], "seeds": args.seeds, "iterations": args.iterations}
    glove_parts, out["unwrap_glove"] = unwrap_figures(examples.glove())
    tip_parts, out["unwrap_fingertip"] = unwrap_figures(examples.fingertip())
    fingers = out["unwrap_glove"]["parts"]
    out["unwrap_target"] = {
        "min_ratio_fingers": min(fingers[f]["mean_ratio_lscm_over_ours"] for f in FINGERS),
        "flipped": sum(p["ours"]["flipped"] for p in fingers.values()),
        "met": bool(min(fingers[f]["mean_ratio_lscm_over_ours"] for f in FINGERS) >= 3.0
                    and all(p["ours"]["flipped"] == 0 for p in fingers.values()))}
    pieces = layers(glove_parts)
    out["nesting"], runs = {}, {}
    for layer, ps in pieces.items():
        out["nesting"][layer], blf, sa = nesting_figures(ps, args.margin, sheet, args.seeds, args.iterations)
        runs[layer] = (blf, sa)
        out["nesting"][layer]["travel"] = travel_figures([s for s in sa[0].shapes])
    n = out["nesting"]
    out["nesting_target"] = {"met": bool(all(v["ratio_sa_best_over_blf_best"] <= 1.15 and v["min_gap_mm"]
                                             >= args.margin - 1e-9 for v in n.values()))}
    path = ROOT / ".bench" / "skin.json"
    path.parent.mkdir(exist_ok=True)
    path.write_text(json.dumps(out, indent=1))
    print(json.dumps({k: out[k] for k in ("unwrap_target", "nesting_target")}, indent=1))
    for layer, v in n.items():
        print(f"{layer}: SA best {v['sa_best_mm2']:.0f} median {v['sa_median_mm2']:.0f}, BLF best "
              f"{v['blf_best_mm2']:.0f} mm^2 (ratio {v['ratio_sa_best_over_blf_best']:.3f} / "
              f"{v['ratio_sa_median_over_blf_best']:.3f}), min gap {v['min_gap_mm']:.3f} mm")
    if args.docs:
        docs = ROOT / "docs"
        sel = [r for r in glove_parts if r.placement.spec.name in ("palm", "index", "thumb")] + tip_parts
        plots.distortion_png(docs / "skin_unwrap.png", [(r.placement.spec.name, r.placement.vertices,
                                                          r.placement.faces, {"stretch-minimizing": r.unwrap.uv,
                                                                              "LSCM (best scale)": r.lscm_uv})
                                                         for r in sel])
        plots.unwrap_loss_png(docs / "skin_unwrap_loss.png", {r.placement.spec.name: r.unwrap.loss
                                                              for r in glove_parts + tip_parts})
        blf, sa = runs["electrodes"]
        best_b = min(blf, key=lambda x: x.area)
        best_s = min(sa, key=lambda x: x.area)
        plots.nesting_loss_png(docs / "skin_nesting_loss.png", [s.loss for s in sa], best_b.area)
        plots.layout_png(docs / "skin_nesting.png", {
            f"electrodes, annealing {best_s.area / 100:.0f} cm2": best_s.shapes,
            f"electrodes, bottom-left fill {best_b.area / 100:.0f} cm2": best_b.shapes,
            "dielectric + markers, annealing": min(runs["dielectric"][1], key=lambda x: x.area).shapes
            + [marker(g) for g in min(runs["dielectric"][1], key=lambda x: x.area).shapes]})
        for name, parts, design, view in (("glove", glove_parts, examples.glove(), (-70, -90)),
                                           ("fingertip", tip_parts, examples.fingertip(), (10, -100))):
            plots.layout_3d_png(docs / f"skin_{name}.png", design.base.vertices, design.base.faces,
                                [(r.placement.spec.name, r.placement.vertices, r.placement.faces) for r in parts],
                                np.vstack([r.placement.cell_position for r in parts]), view)


if __name__ == "__main__":
    main()
