"""``xm skin``: sensor-skin design tools (thesis 4.5.4, 4.8.1).

  xm skin glove [--out DIR]        the glove on the hand model: layout, unwrap, nesting, SVGs, cell map
                 [--palm-cutout R C NR NC]  the palm's cutout (default 4 3 2 3: between thumb and index)
  xm skin fingertip [--out DIR]    the 4x4 fingertip sensor at 45 degrees
  xm skin design MESH --rows R --cols C --pitch P --centre X,Y,Z --normal X,Y,Z [--angle DEG]
                                   one sensor laid on a closed base mesh (OBJ/STL/PLY, mm) by a plane
  xm skin unwrap PART              a part mesh (open, genus 0) unwrapped both ways; report and picture

Every run writes a report.json (distortion per part against LSCM, nesting, toolpaths) and
pictures beside its files; with --cellmap-only a design run places the sensors and writes only
<design>_cellmap.json (`make cellmap`: the glove's into models/skin/, the layout the glove service
and the tactile projection read). Bad input (an open or non-manifold mesh, a layout that does not fit,
parts that cannot be nested) ends with a message naming the part and exit status 2.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from skin import examples, plots
from skin.errors import COUNTS, SkinError
from skin.layout import Carrier, SensorSpec
from skin.mesh import check_sheet, load_base_mesh
from skin.pipeline import Fabrication, fabricate, write_cell_map
from skin.unwrap import distortion, lscm, stretch_minimizing

DEFAULT_OUT = Path("runs/skin")


def _vec(text: str) -> np.ndarray:
    v = np.array([float(x) for x in text.split(",")])
    if v.shape != (3,):
        raise argparse.ArgumentTypeError(f"expected X,Y,Z, got {text!r}")
    return v


def plane_carrier(centre: np.ndarray, normal: np.ndarray, size: tuple[float, float], angle: float,
                  up: np.ndarray | None = None) -> Carrier:
    """A flat sensor of ``size`` (mm, rows x cols) centred at ``centre`` facing along ``normal``,
    its rows turned ``angle`` degrees from the plane's first axis (``up`` projected, default the
    world axis least aligned with the normal)."""
    n = normal / np.linalg.norm(normal)
    a = up if up is not None else np.eye(3)[int(np.argmin(np.abs(n)))]
    e1 = a - (a @ n) * n
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    c, s = np.cos(np.radians(angle)), np.sin(np.radians(angle))
    d1, d2 = c * e1 + s * e2, -s * e1 + c * e2

    def carry(st: np.ndarray) -> np.ndarray:
        return centre + np.outer((st[:, 0] - 0.5) * size[0], d1) + np.outer((st[:, 1] - 0.5) * size[1], d2)

    return carry


def report(fab: Fabrication, out: Path, travel: dict[str, dict[str, float]]) -> dict[str, Any]:
    """report.json and the pictures of a fabrication run."""
    d = fab.design
    parts = {r.placement.spec.name: r.report for r in fab.parts}
    nest = {k: {"pieces": len(n.names), "area_mm2": round(n.area, 1), "width_mm": round(n.width, 1),
                "height_mm": round(n.height, 1), "min_gap_mm": round(n.min_gap, 3),
                "parts_area_mm2": round(sum(g.area for g in n.shapes), 1)} for k, n in fab.nestings.items()}
    plots.distortion_png(out / f"{d.name}_distortion.png",
                         [(r.placement.spec.name, r.placement.vertices, r.placement.faces,
                           {"stretch-minimizing": r.unwrap.uv, "LSCM": r.lscm_uv}) for r in fab.parts])
    plots.unwrap_loss_png(out / f"{d.name}_unwrap_loss.png", {r.placement.spec.name: r.unwrap.loss for r in fab.parts})
    plots.layout_png(out / f"{d.name}_sheets.png", {k: n.shapes for k, n in fab.nestings.items()})
    plots.nesting_loss_png(out / f"{d.name}_nesting_loss.png", [fab.nestings["electrodes"].loss],
                           fab.nestings["electrodes"].area)
    cells = np.vstack([r.placement.cell_position for r in fab.parts])
    plots.layout_3d_png(out / f"{d.name}_layout.png", d.base.vertices, d.base.faces,
                        [(r.placement.spec.name, r.placement.vertices, r.placement.faces) for r in fab.parts],
                        cells, (-70, -90) if d.name == "glove" else (10, -100))
    rep = {"design": d.name, "parts": parts, "nesting": nest, "toolpaths": travel}
    (out / "report.json").write_text(json.dumps(rep, indent=1))
    return rep


def run(design: examples.Design, out: Path, iterations: int, seed: int, margin: float,
        sheet: tuple[float, float]) -> dict[str, Any]:
    out.mkdir(parents=True, exist_ok=True)
    fab = fabricate(design, out, margin, sheet, iterations, seed)
    rep = report(fab, out, fab.travel)
    for name, r in rep["parts"].items():
        o, lo = r["ours"], r["lscm"]
        print(f"{name:>10}: edge distortion mean {o['edge_mean']:.4f} (LSCM {lo['edge_mean']:.4f}, "
              f"{lo['edge_mean'] / max(o['edge_mean'], 1e-12):.1f}x), max {o['edge_max']:.3f} (LSCM "
              f"{lo['edge_max']:.3f}), flipped {o['flipped']}")
    for k, n in rep["nesting"].items():
        print(f"{k:>10}: {n['pieces']} pieces in {n['width_mm']} x {n['height_mm']} mm, gap >= {n['min_gap_mm']} mm")
    print(f"files in {out}")
    return rep


def unwrap_file(path: Path, out: Path) -> dict[str, Any]:
    """Unwrap one part mesh both ways: report and picture."""
    name = path.name
    try:
        mesh = trimesh.load(str(path), force="mesh", process=True)
    except (OSError, ValueError, KeyError, IndexError) as exc:
        raise SkinError("unreadable_mesh", name, f"cannot read the mesh ({exc})") from exc
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    check_sheet(v, f, name)
    u = stretch_minimizing(v, f, name)
    uv_l = lscm(v, f, name)
    rep = {"part": name, "ours": distortion(v, u.uv, f), "lscm": distortion(v, uv_l, f)}
    out.mkdir(parents=True, exist_ok=True)
    plots.distortion_png(out / f"{path.stem}_distortion.png", [(name, v, f, {"stretch-minimizing": u.uv,
                                                                             "LSCM": uv_l})])
    np.savetxt(out / f"{path.stem}_uv.csv", u.uv, delimiter=",", header="u_mm,v_mm", comments="")
    (out / f"{path.stem}_unwrap.json").write_text(json.dumps(rep, indent=1))
    print(json.dumps(rep, indent=1))
    return rep


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="xm skin", description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--out", type=Path, help="output folder (default runs/skin/<design>)")
    common.add_argument("--iterations", type=int, default=4000, help="annealing iterations per layer")
    common.add_argument("--seed", type=int, default=0)
    common.add_argument("--margin", type=float, default=2.0, help="smallest gap between parts on a sheet (mm)")
    common.add_argument("--sheet", type=float, nargs=2, default=(200.0, 300.0), metavar=("W", "H"),
                        help="sheet size (mm); default a cutting mat's 200 x 300")
    common.add_argument("--cellmap-only", action="store_true",
                        help="place the sensors and write only <design>_cellmap.json (seconds)")
    g = sub.add_parser("glove", parents=[common], help="the glove on the hand model")
    g.add_argument("--palm-cutout", type=int, nargs=4, action="append", metavar=("ROW", "COL", "NR", "NC"),
                   help="a block of cells left out of the palm's 6 x 6 (repeatable; default 4 3 2 3)")
    sub.add_parser("fingertip", parents=[common], help="the 4x4 fingertip sensor at 45 degrees")
    d = sub.add_parser("design", parents=[common], help="one sensor laid on a closed base mesh by a plane")
    d.add_argument("mesh", type=Path)
    d.add_argument("--rows", type=int, required=True)
    d.add_argument("--cols", type=int, required=True)
    d.add_argument("--pitch", type=float, required=True, help="cell pitch (mm)")
    d.add_argument("--centre", type=_vec, required=True, help="X,Y,Z (mm) near the surface")
    d.add_argument("--normal", type=_vec, required=True, help="X,Y,Z: the direction the sensor faces")
    d.add_argument("--angle", type=float, default=0.0, help="turn of the rows in the plane (degrees)")
    d.add_argument("--cutout", type=int, nargs=4, action="append", default=[], metavar=("ROW", "COL", "NR", "NC"))
    d.add_argument("--gap", type=float, default=1.0, help="gap between electrodes (mm)")
    u = sub.add_parser("unwrap", help="unwrap one part mesh both ways")
    u.add_argument("part", type=Path)
    u.add_argument("--out", type=Path)
    args = ap.parse_args(argv)
    try:
        if args.cmd == "unwrap":
            unwrap_file(args.part, args.out or DEFAULT_OUT / "unwrap")
            return 0
        if args.cmd == "glove":
            design = examples.glove(palm_cutouts=tuple(tuple(c) for c in args.palm_cutout or [examples.PALM_CUTOUT]))
        elif args.cmd == "fingertip":
            design = examples.fingertip()
        else:
            base = load_base_mesh(args.mesh)
            spec = SensorSpec(args.mesh.stem, "sensor", args.rows, args.cols,
                              cutouts=tuple(tuple(c) for c in args.cutout), gap=args.gap)
            carrier = plane_carrier(args.centre, args.normal, (args.rows * args.pitch, args.cols * args.pitch),
                                    args.angle)
            design = examples.Design(args.mesh.stem, base, [(spec, carrier, base)], (args.rows, args.cols),
                                     ("sensor",))
        out = args.out or DEFAULT_OUT / design.name
        if args.cellmap_only:
            print(f"cell map in {write_cell_map(design, out)}")
        else:
            run(design, out, args.iterations, args.seed, args.margin, tuple(args.sheet))
        return 0
    except SkinError as exc:
        print(f"xm skin: {exc}", file=sys.stderr)
        print(f"xm skin: errors by reason {dict(COUNTS)}", file=sys.stderr)
        return 2
