"""From a design to fabrication files: layout, unwrap, flat parts, nesting per layer, toolpaths.

Layers (each cut from its own sheet): ``electrodes`` (conductive silicone: every sensor's row
electrodes, its column electrodes and its cable's conductors, each group kept as cut, side by side,
for transfer on one carrier film), ``dielectric`` (each sensor's outline and each cable's
insulation) and ``markers``: alignment markers following every dielectric part's outline, placed
like the dielectric sheet, for the mold and for registering the parts during assembly.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh
from shapely import MultiPolygon
from shapely.geometry.base import BaseGeometry

from skin.cellmap import cell_map
from skin.examples import Design
from skin.layout import FlatParts, Placement, flat_parts, place
from skin.nest import Nesting, Piece, anneal, bottom_left_fill, min_gap
from skin.toolpath import write_svg
from skin.unwrap import Unwrap, distortion, lscm, stretch_minimizing

MARKER_OFFSET = 0.4  # mm outside a part's outline (with the width, under half the default margin)
MARKER_WIDTH = 0.4  # mm


@dataclass
class PartResult:
    """One sensor through the pipeline."""

    placement: Placement
    unwrap: Unwrap
    lscm_uv: np.ndarray
    flat: FlatParts
    report: dict[str, dict[str, float | int]]  # "ours" / "lscm" -> distortion()


@dataclass
class Fabrication:
    design: Design
    parts: list[PartResult]
    layers: dict[str, list[Piece]]
    nestings: dict[str, Nesting] = field(default_factory=dict)
    travel: dict[str, dict[str, float]] = field(default_factory=dict)  # per layer: write_svg's figures


def unwrap_parts(design: Design, seed: int = 0) -> list[PartResult]:
    """Place every sensor of a design, unwrap it both ways and cut its flat parts."""
    out = []
    for spec, carrier, surface in design.sensors:
        p = place(spec, carrier, surface)
        u = stretch_minimizing(p.vertices, p.faces, spec.name, seed=seed)
        uv_l = lscm(p.vertices, p.faces, spec.name)
        report = {"ours": distortion(p.vertices, u.uv, p.faces), "lscm": distortion(p.vertices, uv_l, p.faces)}
        out.append(PartResult(p, u, uv_l, flat_parts(p, u.uv), report))
    return out


def layers(parts: list[PartResult]) -> dict[str, list[Piece]]:
    """The pieces of each cut layer (markers follow the dielectric's placement)."""
    el, di = [], []
    for r in parts:
        name, f = r.placement.spec.name, r.flat
        el += [Piece(f"{name}/rows", MultiPolygon(f.rows)), Piece(f"{name}/cols", MultiPolygon(f.cols)),
               Piece(f"{name}/cable", MultiPolygon(f.conductors))]
        di += [Piece(f"{name}/dielectric", f.outline), Piece(f"{name}/cable", f.cable_outline)]
    return {"electrodes": el, "dielectric": di}


def marker(shape: BaseGeometry) -> BaseGeometry:
    """An alignment marker: a band following the part's outline ``MARKER_OFFSET`` mm outside it."""
    outer = shape.buffer(MARKER_OFFSET + MARKER_WIDTH, join_style="mitre")
    return outer.difference(shape.buffer(MARKER_OFFSET, join_style="mitre"))


def write_cell_map(design: Design, out_dir: str | Path) -> Path:
    """Place the design's sensors and write only its cell map, ``<out_dir>/<design>_cellmap.json``
    (no unwrap, nesting or toolpaths)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"{design.name}_cellmap.json"
    cell_map(design, [place(spec, carrier, surface) for spec, carrier, surface in design.sensors]).save(path)
    return path


def fabricate(design: Design, out_dir: str | Path, margin: float = 2.0, sheet: tuple[float, float] = (200.0, 300.0),
              iterations: int = 4000, seed: int = 0) -> Fabrication:
    """The whole chain for a design, files under ``out_dir``: the base mesh and part meshes (OBJ),
    the cell map (JSON), one SVG per layer. Returns everything for reports and pictures."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    parts = unwrap_parts(design, seed)
    fab = Fabrication(design, parts, layers(parts))
    design.base.export(out / f"{design.name}_base.obj")
    trimesh.util.concatenate([trimesh.Trimesh(r.placement.vertices, r.placement.faces, process=False)
                              for r in parts]).export(out / f"{design.name}_parts.obj")
    cell_map(design, [r.placement for r in parts]).save(out / f"{design.name}_cellmap.json")
    for layer, pieces in fab.layers.items():
        fab.nestings[layer] = anneal(pieces, margin, sheet, iterations, seed)
    n = fab.nestings["dielectric"]  # markers are placed with the dielectric parts they follow
    bands = [marker(g) for g in n.shapes]
    fab.nestings["markers"] = Nesting(n.names, n.angle, n.offset, bands, n.width, n.height, n.area, min_gap(bands))
    for layer, nest in fab.nestings.items():
        fab.travel[layer] = write_svg(out / f"{design.name}_{layer}.svg", nest.shapes, nest.names, layer)
    return fab


def baseline(pieces: list[Piece], margin: float, sheet: tuple[float, float], seed: int) -> Nesting:
    """Bottom-left fill for a seed: the strip width and the order of near-equal areas drawn at random."""
    rng = np.random.default_rng(seed)
    areas = np.array([p.shape.area for p in pieces])
    order = list(np.argsort(-areas * rng.uniform(0.8, 1.25, len(pieces))))
    widest = max(min(p.shape.bounds[2] - p.shape.bounds[0], p.shape.bounds[3] - p.shape.bounds[1]) for p in pieces)
    width = rng.uniform(min(max(widest, np.sqrt(1.2 * areas.sum())), sheet[0]), sheet[0])
    return bottom_left_fill(pieces, margin, width, sheet[1], order)
