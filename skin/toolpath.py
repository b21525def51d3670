"""Cutting-plotter toolpaths: one SVG per layer, in mm, for a cutting plotter's Inkscape extension
(e.g. inkscape-silhouette, which cuts a document's paths in document order).

Every closed contour of every part becomes one path, viewed from the part's outer surface (the
unwrap keeps faces counter-clockwise seen from outside; SVG's y axis points down, so y is
mirrored onto the sheet). Order: a part's holes before its outline (a part cut free first could
shift), and between parts the nearest next contour (greedy), each contour started at its vertex
nearest the knife, which keeps travel short.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
from shapely import MultiPolygon, Polygon
from shapely.geometry.base import BaseGeometry

BORDER = 5.0  # mm of empty sheet around the parts
INKSCAPE = "http://www.inkscape.org/namespaces/inkscape"
ET.register_namespace("inkscape", INKSCAPE)
ET.register_namespace("", "http://www.w3.org/2000/svg")


def contours(shape: BaseGeometry) -> list[list[np.ndarray]]:
    """Per polygon of a shape: its holes, then its outline (each (k,2), open ring)."""
    polys = list(shape.geoms) if isinstance(shape, MultiPolygon) else [shape] if isinstance(shape, Polygon) else []
    return [[np.asarray(r.coords)[:-1] for r in p.interiors] + [np.asarray(p.exterior.coords)[:-1]] for p in polys]


def order(groups: list[list[np.ndarray]], start: np.ndarray | None = None
          ) -> tuple[list[tuple[int, np.ndarray]], float]:
    """Contours in cutting order (group index, contour) and the knife's travel (mm, pen up): groups
    (a polygon's holes then outline) stay together; the next group is the one whose first contour
    comes nearest."""
    pos = np.zeros(2) if start is None else np.asarray(start, float)
    left = list(range(len(groups)))
    out, travel = [], 0.0
    while left:
        dists = [np.linalg.norm(groups[g][0] - pos, axis=1).min() for g in left]
        g = left.pop(int(np.argmin(dists)))
        for ring in groups[g]:
            k = int(np.argmin(np.linalg.norm(ring - pos, axis=1)))
            ring = np.roll(ring, -k, axis=0)
            travel += float(np.linalg.norm(ring[0] - pos))
            out.append((g, ring))
            pos = ring[0]  # a closed contour ends where it starts
    return out, travel


def travel_in_given_order(groups: list[list[np.ndarray]]) -> float:
    """The knife's travel cutting the contours as listed, each from its first vertex (the baseline)."""
    pos, travel = np.zeros(2), 0.0
    for group in groups:
        for ring in group:
            travel += float(np.linalg.norm(ring[0] - pos))
            pos = ring[0]
    return travel


def write_svg(path: str | Path, shapes: list[BaseGeometry], names: list[str], layer: str) -> dict[str, float]:
    """Write one layer's placed shapes as an SVG (mm); returns the sheet size and knife travel."""
    groups, owner = [], []
    for shape, name in zip(shapes, names, strict=True):
        for g in contours(shape):
            groups.append(g)
            owner.append(name)
    allpts = np.vstack([r for g in groups for r in g])
    lo, hi = allpts.min(axis=0), allpts.max(axis=0)
    W, H = hi - lo + 2 * BORDER

    def sheet(p: np.ndarray) -> np.ndarray:
        return np.stack([p[:, 0] - lo[0] + BORDER, hi[1] - p[:, 1] + BORDER], axis=1)

    groups = [[sheet(r) for r in g] for g in groups]
    rings, travel = order(groups)
    svg = ET.Element("{http://www.w3.org/2000/svg}svg", {"width": f"{W:.3f}mm", "height": f"{H:.3f}mm",
                                                         "viewBox": f"0 0 {W:.3f} {H:.3f}", "version": "1.1"})
    g = ET.SubElement(svg, "{http://www.w3.org/2000/svg}g", {f"{{{INKSCAPE}}}groupmode": "layer",
                                                            f"{{{INKSCAPE}}}label": layer, "id": f"layer-{layer}"})
    for k, (group, ring) in enumerate(rings):
        d = "M " + " L ".join(f"{x:.3f},{y:.3f}" for x, y in ring) + " Z"
        ET.SubElement(g, "{http://www.w3.org/2000/svg}path", {
            "d": d, "id": f"{layer}-{k}", f"{{{INKSCAPE}}}label": owner[group],
            "style": "fill:none;stroke:#ff0000;stroke-width:0.1"})
    ET.ElementTree(svg).write(path, encoding="utf-8", xml_declaration=True)
    return {"width_mm": float(W), "height_mm": float(H), "travel_mm": travel,
            "travel_unordered_mm": travel_in_given_order(groups), "paths": len(rings)}
