"""A sensor matrix laid out on a base mesh (thesis 4.5.4, 4.8.1).

A sensor is a rows x columns matrix of cells; row electrodes run along the rows (one strip per
row, across every column), column electrodes across them on the other side of the dielectric, and
a cell is a crossing. Cutouts remove cells (the glove palm's 2x3 corner between thumb and index).

Where the matrix lies is given by a *carrier*: a function from the sensor's unit square (s down the
rows, t along the columns, both 0..1) to points in space on or near the base mesh, as the layout
mesh in a CAD tool is drawn over the base mesh. ``place`` samples the square on a grid
(``subdiv`` quads per cell side), maps it through the carrier and projects every point onto the
base mesh (closest point), which gives the part's surface patch; points that land too far from the
carrier, and patch faces that collapse or turn over in the projection, mean the layout does not
fit the surface.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import trimesh
from shapely import MultiPolygon, Polygon, box, unary_union

from skin.errors import SkinError

Carrier = Callable[[np.ndarray], np.ndarray]  # (n,2) unit-square (s,t) -> (n,3) points, mm


@dataclass(frozen=True)
class SensorSpec:
    """One sensor matrix: its cells, where they sit in the readout matrix and its electrodes.

    ``row0`` / ``col0``: the readout matrix's excitation line / reception line of the sensor's first
    row / column. ``cutouts``: (row, col, rows, cols) blocks of cells left out. ``gap``: mm between
    neighbouring electrodes, kept even over the curved surface. The flat cable carries one conductor
    per electrode, ``conductor`` wide with ``conductor_gap`` between, ``cable_length`` long."""

    name: str
    region: str
    rows: int
    cols: int
    row0: int = 0
    col0: int = 0
    cutouts: tuple[tuple[int, int, int, int], ...] = ()
    gap: float = 1.0
    subdiv: int = 4
    conductor: float = 0.5
    conductor_gap: float = 0.5
    cable_length: float = 40.0

    def populated(self) -> np.ndarray:
        """(rows, cols) bool: which cells exist."""
        cells = np.ones((self.rows, self.cols), bool)
        for r, c, nr, nc in self.cutouts:
            cells[r:r + nr, c:c + nc] = False
        return cells


@dataclass
class Placement:
    """A sensor on the base mesh: its surface patch (triangles over the grid of its unit square),
    each patch vertex's grid index, and its cells' centres and normals on the surface (mm)."""

    spec: SensorSpec
    st: np.ndarray  # (V,2) unit-square coordinates of the patch vertices
    vertices: np.ndarray  # (V,3) on the base mesh
    faces: np.ndarray  # (F,3), wound outward (counter-clockwise seen from outside)
    grid_id: np.ndarray  # (rows*subdiv+1, cols*subdiv+1) patch vertex id of each grid node, -1: cut out
    cells: np.ndarray  # (C,2) sensor row, column of every populated cell
    cell_position: np.ndarray  # (C,3)
    cell_normal: np.ndarray  # (C,3)
    offset: dict[str, float] = field(default_factory=dict)  # projection distances: max, mean (mm)


def _check_spec(spec: SensorSpec) -> None:
    if spec.rows < 1 or spec.cols < 1 or spec.subdiv < 1:
        raise SkinError("bad_layout", spec.name, f"a sensor needs at least 1x1 cells and subdiv >= 1, got "
                        f"{spec.rows}x{spec.cols}, subdiv {spec.subdiv}")
    cells = spec.populated()
    if not cells.any():
        raise SkinError("bad_layout", spec.name, "the cutouts remove every cell")
    for r in range(spec.rows):
        _contiguous(cells[r], spec.name, "row", r)
    for c in range(spec.cols):
        _contiguous(cells[:, c], spec.name, "column", c)


def _contiguous(line: np.ndarray, name: str, what: str, k: int) -> None:
    """An electrode strip must stay one piece: its populated cells must be contiguous."""
    idx = np.flatnonzero(line)
    if len(idx) == 0:
        raise SkinError("bad_layout", name, f"{what} {k} has no cells left after the cutouts")
    if idx[-1] - idx[0] + 1 != len(idx):
        raise SkinError("split_electrode", name, f"a cutout cuts {what} {k}'s electrode in two pieces")


def _grid(spec: SensorSpec) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit-square coordinates of the used grid nodes, triangles over the populated cells and the
    grid-node -> vertex id table."""
    k, R, C = spec.subdiv, spec.rows, spec.cols
    cells = spec.populated()
    ni, nj = R * k + 1, C * k + 1
    quad_used = np.repeat(np.repeat(cells, k, axis=0), k, axis=1)  # (R k, C k)
    node_used = np.zeros((ni, nj), bool)
    for di in (0, 1):
        for dj in (0, 1):
            node_used[di:ni - 1 + di, dj:nj - 1 + dj] |= quad_used
    grid_id = np.full((ni, nj), -1)
    grid_id[node_used] = np.arange(node_used.sum())
    ii, jj = np.nonzero(node_used)
    st = np.stack([ii / (R * k), jj / (C * k)], axis=1)
    qi, qj = np.nonzero(quad_used)
    a, b = grid_id[qi, qj], grid_id[qi, qj + 1]
    c, d = grid_id[qi + 1, qj + 1], grid_id[qi + 1, qj]
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return st, faces, grid_id


def _areas(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Face areas and unit normals."""
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    a = np.linalg.norm(n, axis=1)
    return a / 2, n / np.maximum(a, 1e-12)[:, None]


def place(spec: SensorSpec, carrier: Carrier, surface: trimesh.Trimesh, tolerance: float = 5.0) -> Placement:
    """Project a sensor's layout onto ``surface`` (the part of the base mesh it lies on). Raises
    SkinError naming the sensor where the layout does not fit: carrier points over ``tolerance`` mm
    from the surface, patch faces shrunk below a quarter of their carrier area or turned over."""
    _check_spec(spec)
    st, faces, grid_id = _grid(spec)
    carried = np.asarray(carrier(st), float)
    if carried.shape != (len(st), 3) or not np.isfinite(carried).all():
        raise SkinError("bad_layout", spec.name, "the carrier returned no finite 3-D point per layout point")
    on, dist, tri = trimesh.proximity.closest_point(surface, carried)
    far = dist > tolerance
    if far.any():
        worst = int(np.argmax(dist))
        raise SkinError("does_not_fit", spec.name, f"the layout does not fit the surface: {far.sum()} of {len(st)} "
                        f"layout points lie more than {tolerance} mm from it (worst {dist[worst]:.1f} mm at row "
                        f"{st[worst, 0] * spec.rows:.1f}, column {st[worst, 1] * spec.cols:.1f})")
    a0, n0 = _areas(carried, faces)
    a1, n1 = _areas(on, faces)
    outward = np.einsum("ij,ij->i", n1, surface.face_normals[tri[faces[:, 0]]]).sum()
    if outward < 0:  # the grid's own winding faces inward here: flip so patches face outward
        faces = faces[:, ::-1].copy()
        n0, n1 = -n0, -n1
    bad = (a1 < 0.25 * a0) | (np.einsum("ij,ij->i", n0, n1) < 0)
    if bad.any():
        f = int(np.flatnonzero(bad)[0])
        s, t = st[faces[f]].mean(axis=0)
        raise SkinError("does_not_fit", spec.name, f"the layout does not fit the surface: {bad.sum()} patch faces "
                        f"collapse or turn over when projected (first near row {s * spec.rows:.1f}, column "
                        f"{t * spec.cols:.1f})")
    cells = np.argwhere(spec.populated())
    centre = (cells + 0.5) / [spec.rows, spec.cols]
    pos, _, ctri = trimesh.proximity.closest_point(surface, np.asarray(carrier(centre), float))
    return Placement(spec, st, on, faces, grid_id, cells, pos, surface.face_normals[ctri],
                     {"max": float(dist.max()), "mean": float(dist.mean())})


def cell_polygon(p: Placement, uv: np.ndarray, r: int, c: int) -> Polygon:
    """The outline of cell (r, c) in the unwrapped plane: its grid nodes along its four sides."""
    k = p.spec.subdiv
    i0, j0 = r * k, c * k
    ring = [p.grid_id[i0, j0 + m] for m in range(k)] + [p.grid_id[i0 + m, j0 + k] for m in range(k)]
    ring += [p.grid_id[i0 + k, j0 + k - m] for m in range(k)] + [p.grid_id[i0 + k - m, j0] for m in range(k)]
    poly = Polygon(uv[ring])
    return poly if poly.is_valid else poly.buffer(0)


@dataclass
class FlatParts:
    """A sensor's shapes in the unwrapped plane (mm): the dielectric outline, the row and column
    electrodes (one strip each, evenly separated), and its flat cable (outline and conductors)."""

    outline: Polygon
    rows: list[Polygon]
    cols: list[Polygon]
    cable_outline: Polygon
    conductors: list[Polygon]


def flat_parts(p: Placement, uv: np.ndarray) -> FlatParts:
    """Electrodes from the unwrapped patch: each strip is the union of its cells shrunk by half the
    gap on every side, so neighbouring strips stay ``gap`` apart (measured in the flat, which the
    stretch-minimizing unwrap keeps true to the surface) and half a gap inside the outline."""
    spec, cells = p.spec, p.spec.populated()
    poly = {(r, c): cell_polygon(p, uv, r, c) for r, c in np.argwhere(cells)}
    outline = unary_union(list(poly.values()))
    if not isinstance(outline, Polygon):
        raise SkinError("bad_layout", spec.name, "the unwrapped cells do not form one outline")

    def strip(keys: list[tuple[int, int]], what: str) -> Polygon:
        shape = unary_union([poly[k] for k in keys]).buffer(-spec.gap / 2, join_style="mitre")
        if isinstance(shape, MultiPolygon):  # a sliver where the strip narrows: keep the body
            shape = max(shape.geoms, key=lambda g: g.area)
        if shape.is_empty:
            raise SkinError("bad_layout", spec.name, f"{what} is narrower than the electrode gap {spec.gap} mm")
        return shape

    rows = [strip([(r, c) for c in range(spec.cols) if cells[r, c]], f"row {r}") for r in range(spec.rows)]
    cols = [strip([(r, c) for r in range(spec.rows) if cells[r, c]], f"column {c}") for c in range(spec.cols)]
    n = spec.rows + spec.cols  # one conductor per electrode, alternating with gaps
    pitch = spec.conductor + spec.conductor_gap
    width = n * pitch + spec.conductor_gap
    conductors = [box(spec.conductor_gap + i * pitch, 0.0, spec.conductor_gap + i * pitch + spec.conductor,
                      spec.cable_length) for i in range(n)]
    return FlatParts(outline, rows, cols, box(0.0, 0.0, width, spec.cable_length), conductors)
