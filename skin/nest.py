"""Nesting the flat parts on a sheet (thesis 4.5.4): simulated annealing, and bottom-left fill.

Parts can be highly non-convex (a palm sensor with a cutout, electrode combs), so both methods
work on the exact shapes: every distance is shapely's exact polygon distance, and two parts are
never closer than ``margin`` (mm). Each annealing move changes one part (or swaps two): slide a
part on the bounding rectangle's edge toward its middle as far as it stays free, relocate such a
part anywhere inside the rectangle in any quarter turn, swap two parts' places, turn a part by a
quarter or a few degrees, or shift it. Only layouts that keep the margin and fit the sheet are
kept; a larger combined bounding rectangle is accepted with the Metropolis probability at a
temperature that decays geometrically. The annealer starts from plain shelves (parts laid along
their long side, in rows by height), and from the baseline only where shelves do not fit the
sheet. The baseline is bottom-left fill: parts in order of decreasing area, each at the lowest
then leftmost free position of a strip (candidate corners from the parts already placed, then
slid down and left), trying four quarter turns.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import shapely
from shapely import STRtree
from shapely.affinity import rotate, translate
from shapely.geometry.base import BaseGeometry

from skin.errors import SkinError


@dataclass
class Piece:
    """A part to cut: its name and shape (mm), any orientation; nesting places it rigidly."""

    name: str
    shape: BaseGeometry


@dataclass
class Nesting:
    """Where every piece goes: turn (degrees about its centroid) then shift; the placed shapes, the
    combined bounding rectangle's size and area, the smallest gap between two pieces (exact) and
    the loss history (area per iteration: current, best)."""

    names: list[str]
    angle: np.ndarray
    offset: np.ndarray  # (n,2)
    shapes: list[BaseGeometry]
    width: float
    height: float
    area: float
    min_gap: float
    loss: list[tuple[float, float]] = field(default_factory=list)


def _centred(pieces: list[Piece]) -> list[BaseGeometry]:
    out = []
    for p in pieces:
        if p.shape.is_empty or not p.shape.is_valid or p.shape.area <= 0:
            raise SkinError("bad_part", p.name, "the part's shape is empty or invalid")
        c = p.shape.centroid
        out.append(translate(p.shape, -c.x, -c.y))
    return out


def _place(shape: BaseGeometry, angle: float, x: float, y: float) -> BaseGeometry:
    return translate(rotate(shape, angle, origin=(0, 0)), x, y)


def min_gap(shapes: list[BaseGeometry]) -> float:
    """The smallest exact distance between any two shapes (inf for fewer than two)."""
    arr = np.array(shapes, dtype=object)
    best = np.inf
    for i in range(len(arr) - 1):
        best = min(best, float(shapely.distance(arr[i + 1:], arr[i]).min()))
    return best


def check_fits(pieces: list[Piece], sheet: tuple[float, float], margin: float, layer: str) -> None:
    """Every piece must fit the sheet in some quarter turn, and all of them together must have a
    chance to: SkinError naming the piece (or the layer) otherwise."""
    W, H = sheet
    total = 0.0
    for p in pieces:
        x0, y0, x1, y1 = p.shape.bounds
        w, h = x1 - x0, y1 - y0
        rect = p.shape.minimum_rotated_rectangle
        edges = np.diff(np.asarray(rect.exterior.coords)[:3], axis=0) if rect.geom_type == "Polygon" else None
        mw, mh = (sorted(np.linalg.norm(edges, axis=1)) if edges is not None else (w, h))
        if not any(a <= W and b <= H for a, b in ((w, h), (h, w), (mw, mh), (mh, mw))):
            raise SkinError("cannot_nest", p.name, f"the part ({w:.1f} x {h:.1f} mm) does not fit the "
                            f"{W:.0f} x {H:.0f} mm sheet in any orientation")
        total += shapely.buffer(p.shape, margin / 2).area
    if total > W * H:
        raise SkinError("cannot_nest", layer, f"the parts with their margins need {total:.0f} mm^2, the "
                        f"{W:.0f} x {H:.0f} mm sheet has {W * H:.0f} mm^2")


def _result(names: list[str], base: list[BaseGeometry], angle: np.ndarray, offset: np.ndarray,
            loss: list[tuple[float, float]]) -> Nesting:
    shapes = [_place(g, a, x, y) for g, a, (x, y) in zip(base, angle, offset, strict=True)]
    x0, y0, x1, y1 = shapely.total_bounds(np.array(shapes, dtype=object))
    return Nesting(names, angle, offset, shapes, x1 - x0, y1 - y0, (x1 - x0) * (y1 - y0), min_gap(shapes), loss)


def _bounds(shapes: list[BaseGeometry]) -> np.ndarray:
    return shapely.bounds(np.array(shapes, dtype=object))


def _area(b: np.ndarray) -> tuple[float, float, float]:
    w, h = b[:, 2].max() - b[:, 0].min(), b[:, 3].max() - b[:, 1].min()
    return w * h, w, h


def bottom_left_fill(pieces: list[Piece], margin: float = 2.0, width: float = 200.0, height: float = 300.0,
                     order: list[int] | None = None) -> Nesting:
    """Bottom-left fill on a strip ``width`` wide (pieces in ``order``, default decreasing area)."""
    check_fits(pieces, (width, height), margin, "sheet")
    base = _centred(pieces)
    order = order if order is not None else list(np.argsort([-g.area for g in base]))
    angle, offset = np.zeros(len(base)), np.zeros((len(base), 2))
    placed: list[BaseGeometry] = []
    for i in order:
        best = None
        tree = STRtree(placed) if placed else None

        def free(g: BaseGeometry, tree: STRtree | None = tree) -> bool:
            return tree is None or len(tree.query(g, predicate="dwithin", distance=margin)) == 0

        pb = _bounds(placed) if placed else np.zeros((0, 4))
        for a in (0.0, 90.0, 180.0, 270.0):
            g = rotate(base[i], a, origin=(0, 0))
            x0, y0, x1, y1 = g.bounds
            w, h = x1 - x0, y1 - y0
            if w > width:
                continue
            xs = np.unique(np.r_[0.0, pb[:, 2] + margin])
            ys = np.unique(np.r_[0.0, pb[:, 3] + margin])
            cand = sorted((y, x) for y in ys for x in xs if x + w <= width and y + h <= height)
            for y, x in cand:
                if best is not None and y >= best[0]:
                    break
                dx, dy = x - x0, y - y0
                if not free(translate(g, dx, dy)):
                    continue
                dx, dy = _slide(g, dx, dy, x0, y0, free)
                top = dy + y1
                if best is None or (top, dx + x0) < (best[0], best[1]):
                    best = (top, dx + x0, a, dx, dy)
                break
        if best is None:
            raise SkinError("cannot_nest", pieces[i].name, f"no free place left on the {width:.0f} x "
                            f"{height:.0f} mm sheet")
        _, _, angle[i], offset[i, 0], offset[i, 1] = best
        placed.append(_place(base[i], angle[i], *offset[i]))
    return _result([p.name for p in pieces], base, angle, offset, [])


def _slide(g: BaseGeometry, dx: float, dy: float, x0: float, y0: float, free) -> tuple[float, float]:
    """Slide a free piece down, then left, as far as it stays free (bisection), twice."""
    for _ in range(2):
        for axis in (1, 0):
            lo, hi = 0.0, (dy + y0) if axis else (dx + x0)  # distance to the sheet's edge
            for _ in range(10):
                mid = (lo + hi) / 2
                t = (dx, dy - mid) if axis else (dx - mid, dy)
                lo, hi = (mid, hi) if free(translate(g, *t)) else (lo, mid)
            dx, dy = (dx, dy - lo) if axis else (dx - lo, dy)
    return dx, dy


def _lying(g: BaseGeometry) -> float:
    """The turn (degrees) that lays a shape's minimum rotated rectangle long side along x."""
    rect = g.minimum_rotated_rectangle
    if rect.geom_type != "Polygon":
        return 0.0
    e = np.diff(np.asarray(rect.exterior.coords)[:3], axis=0)
    k = int(np.argmax(np.linalg.norm(e, axis=1)))
    return float(-np.degrees(np.arctan2(e[k, 1], e[k, 0])))


def _shelves(base: list[BaseGeometry], margin: float, width: float) -> tuple[np.ndarray, np.ndarray]:
    """A plain start: every piece laid along its long side, by decreasing height in rows ``width``
    wide (bounding boxes + margin). Returns turns and shifts."""
    angle = np.array([_lying(g) for g in base])
    b = _bounds([rotate(g, a, origin=(0, 0)) for g, a in zip(base, angle, strict=True)])
    size = b[:, 2:] - b[:, :2]
    offset = np.zeros((len(base), 2))
    x = y = row_h = 0.0
    for i in np.argsort(-size[:, 1]):
        if x > 0 and x + size[i, 0] > width:
            x, y, row_h = 0.0, y + row_h + margin, 0.0
        offset[i] = [x - b[i, 0], y - b[i, 1]]
        x += size[i, 0] + margin
        row_h = max(row_h, size[i, 1])
    return angle, offset


class _State:
    """The annealer's current layout: turns, shifts, placed shapes and their bounds."""

    def __init__(self, base: list[BaseGeometry], angle: np.ndarray, offset: np.ndarray, margin: float) -> None:
        self.base, self.angle, self.offset, self.margin = base, angle.copy(), offset.copy(), margin
        self.shapes = np.array([_place(g, a, *o) for g, a, o in zip(base, angle, offset, strict=True)], dtype=object)
        self.bounds = _bounds(list(self.shapes))
        self.area = _area(self.bounds)[0]

    def free(self, moved: dict[int, BaseGeometry]) -> bool:
        """Whether moved pieces keep the margin to every other piece and to each other."""
        keep = np.ones(len(self.base), bool)
        keep[list(moved)] = False
        rest = self.shapes[keep]
        for k, g in moved.items():
            if shapely.dwithin(rest, g, self.margin).any():
                return False
            if any(shapely.dwithin(moved[m], g, self.margin) for m in moved if m > k):
                return False
        return True

    def slide(self, i: int, direction: np.ndarray, reach: float) -> tuple[float, float, float]:
        """Piece i moved along ``direction`` as far as it stays free (bisection up to ``reach``)."""
        lo, hi = 0.0, reach
        g = self.shapes[i]
        for _ in range(8):
            mid = (lo + hi) / 2
            lo, hi = (mid, hi) if self.free({i: translate(g, *(mid * direction))}) else (lo, mid)
        return (self.angle[i], *(self.offset[i] + lo * direction))


def _propose(st: _State, rng: np.random.Generator, frac: float, scale: float) -> list[tuple[int, float, float, float]]:
    """One random move: (piece, turn, x, y) for each piece it changes."""
    n = len(st.base)
    i = int(rng.integers(n))
    lo, hi = st.bounds[:, :2].min(axis=0), st.bounds[:, 2:].max(axis=0)
    on_edge = np.flatnonzero((np.isclose(st.bounds[:, :2], lo) | np.isclose(st.bounds[:, 2:], hi)).any(axis=1))
    kind = rng.random()
    if kind < 0.3:  # slide a piece on the rectangle's edge toward the middle, as far as it goes
        i = int(rng.choice(on_edge))
        d = (lo + hi) / 2 - st.offset[i] + rng.normal(0, 0.3 * scale, 2)
        dist = float(np.linalg.norm(d))
        return [(i, *st.slide(i, d / max(dist, 1e-9), dist))] if dist > 1e-6 else []
    if kind < 0.5:  # relocate a piece on the edge anywhere inside the rectangle, any quarter turn
        i = int(rng.choice(on_edge))
        return [(i, (st.angle[i] + rng.choice([0.0, 90.0, 180.0, 270.0])) % 360, *rng.uniform(lo, hi))]
    if kind < 0.6 and n > 1:  # swap two pieces' places
        j = int(rng.integers(n - 1))
        j += j >= i
        return [(i, st.angle[i], *st.offset[j]), (j, st.angle[j], *st.offset[i])]
    if kind < 0.75:  # turn by a quarter or a few degrees
        da = rng.choice([90.0, 180.0, 270.0]) if rng.random() < 0.5 else rng.normal(0, 10 * (1 - frac) + 1)
        return [(i, (st.angle[i] + da) % 360, *st.offset[i])]
    return [(i, st.angle[i], *(st.offset[i] + rng.normal(0, scale * (0.5 * (1 - frac) + 0.02), 2)))]


def anneal(pieces: list[Piece], margin: float = 2.0, sheet: tuple[float, float] = (200.0, 300.0),
           iterations: int = 4000, seed: int = 0, t0: float = 0.03, t1: float = 2e-4) -> Nesting:
    """Simulated annealing of the pieces' turns and shifts, minimising the combined bounding
    rectangle's area with every pairwise distance at least ``margin`` (exact) inside the sheet."""
    check_fits(pieces, sheet, margin, "sheet")
    W, H = sheet
    rng = np.random.default_rng(seed)
    base = _centred(pieces)
    n = len(base)
    angle, offset = _shelves(base, margin, W)
    st = _State(base, angle, offset, margin)
    _, w, h = _area(st.bounds)
    if w > W or h > H or min_gap(list(st.shapes)) < margin:  # shelves too tall: start from bottom-left fill
        start = bottom_left_fill(pieces, margin, W, H)
        st = _State(base, start.angle, start.offset, margin)
    scale = np.sqrt(sum(g.area for g in base) / n)
    area0 = st.area
    best = (st.area, st.angle.copy(), st.offset.copy())
    loss = []
    for it in range(iterations):
        frac = it / max(iterations - 1, 1)
        T = t0 * (t1 / t0) ** frac
        moves = _propose(st, rng, frac, scale)
        new = {k: _place(base[k], a, x, y) for k, a, x, y in moves}
        if new and st.free(new):
            nb = st.bounds.copy()
            for k, g in new.items():
                nb[k] = g.bounds
            new_area, nw, nh = _area(nb)
            if nw <= W and nh <= H and (new_area <= st.area or rng.random() < np.exp(-(new_area - st.area)
                                                                                   / (area0 * T))):
                for k, a, x, y in moves:
                    st.angle[k], st.offset[k] = a, (x, y)
                    st.shapes[k] = new[k]
                st.bounds, st.area = nb, new_area
                if st.area < best[0]:
                    best = (st.area, st.angle.copy(), st.offset.copy())
        loss.append((st.area, best[0]))
    out = _result([p.name for p in pieces], base, best[1], best[2], loss)
    if out.min_gap < margin - 1e-9:  # cannot happen: every accepted layout was checked
        raise SkinError("margin_violated", "sheet", f"nesting left two parts {out.min_gap:.3f} mm apart")
    return out
