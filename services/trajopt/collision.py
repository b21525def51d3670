"""Collision geometry for the trajectory optimizer (thesis 7.20, 7.21), pure.

Convex shapes come from the URDF (boxes, cylinders, spheres, convex meshes). For every selected
pair of shapes and every free knot, the constraint is a separating plane between two points, one
fixed to each link: with unit normal n (from shape A to shape B) and witness points a (on A) and
b (on B),

    n . (b(q) - a(q)) >= margin,

which at the linearisation point equals the signed distance, and whose gradient is the signed
distance's gradient (the witness points move with their links; the plane is held per SQP
iteration). Normals and witness points are recomputed at every SQP iterate: by coal's GJK (EPA when
the shapes overlap, giving a negative distance) for pairs whose covering spheres come within
``near``, and from the closest pair of covering spheres otherwise (a conservative plane whose value
is a lower bound of the distance, at a fraction of the cost). The optimizer gives its few
constraint slots per knot to the closest pairs and checks every pair at the final iterate.
"""

from __future__ import annotations

from dataclasses import dataclass

import coal
import numpy as np

from shared.kinematics import RobotModel, Shape


def coal_geometry(shape: Shape):
    """The coal collision object of a URDF shape (meshes as their convex hull)."""
    if shape.kind == "box":
        return coal.Box(*shape.size)
    if shape.kind == "cylinder":
        return coal.Cylinder(float(shape.size[0]), float(shape.size[1]))
    if shape.kind == "sphere":
        return coal.Sphere(float(shape.size[0]))
    if shape.kind == "mesh":
        pts = coal.StdVec_Vec3s()
        for v in shape.vertices:
            pts.append(np.asarray(v, float))
        return coal.Convex.convexHull(pts, True, None)
    raise ValueError(f"no collision geometry for shape kind {shape.kind!r}")


def bounding_spheres(shape: Shape, most: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Spheres covering the shape (centres (m,3) in the shape frame, radii (m,)): long boxes and
    cylinders are cut into up to ``most`` segments along their longest axis (tighter bounds)."""
    if shape.kind == "sphere":
        return np.zeros((1, 3)), np.array([float(shape.size[0])])
    if shape.kind == "cylinder":
        r, length = float(shape.size[0]), float(shape.size[1])
        m = min(most, max(1, int(np.ceil(length / (2 * r)))))
        z = (np.arange(m) + 0.5) * length / m - length / 2
        return np.stack([np.zeros(m), np.zeros(m), z], 1), np.full(m, np.hypot(r, length / (2 * m)))
    if shape.kind == "box":
        centre, dims = np.zeros(3), np.asarray(shape.size, float)
    else:  # mesh: its bounding box
        lo, hi = shape.vertices.min(axis=0), shape.vertices.max(axis=0)
        centre, dims = (lo + hi) / 2, hi - lo
    axis = int(np.argmax(dims))
    second = max(np.sort(dims)[-2], 1e-3)
    m = min(most, max(1, int(np.ceil(dims[axis] / second))))
    seg = dims.copy()
    seg[axis] = dims[axis] / m
    centres = np.tile(centre, (m, 1))
    centres[:, axis] += (np.arange(m) + 0.5) * seg[axis] - dims[axis] / 2
    return centres, np.full(m, np.linalg.norm(seg) / 2)


@dataclass
class ShapePair:
    a: Shape
    b: Shape
    geom_a: object
    geom_b: object
    solver: object  # coal.ComputeDistance; it keeps raw pointers, so the geometries live here too


@dataclass
class Witnesses:
    """Per pair and knot: normal (world), witness points in their link frames, signed distance."""
    normal: np.ndarray  # (pairs, knots, 3)
    local_a: np.ndarray  # (pairs, knots, 3)
    local_b: np.ndarray
    distance: np.ndarray  # (pairs, knots); a lower bound where the bounding spheres were used
    exact: np.ndarray  # (pairs, knots) bool: from GJK/EPA


class CollisionModel:
    """Shape pairs between the given link pairs of a model, and their separating planes."""

    def __init__(self, model: RobotModel, link_pairs: list[tuple[str, str]], near: float = 0.02) -> None:
        self.model = model
        self.near = near  # lower-bound gap under which GJK/EPA computes the exact separation
        self.pairs: list[ShapePair] = []
        for la, lb in link_pairs:
            for a in model.shapes_of(la):
                for b in model.shapes_of(lb):
                    ga, gb = coal_geometry(a), coal_geometry(b)
                    self.pairs.append(ShapePair(a, b, ga, gb, coal.ComputeDistance(ga, gb)))
        self.links = sorted({p.a.link for p in self.pairs} | {p.b.link for p in self.pairs})
        self.link_a = np.array([self.links.index(p.a.link) for p in self.pairs], int)
        self.link_b = np.array([self.links.index(p.b.link) for p in self.pairs], int)
        # covering spheres of every shape in a pair, in their link frames, and every
        # (pair, sphere of a, sphere of b) combination as a padded (pairs, combos) table
        centres, radii, owner, combos, known = [], [], [], [], {}
        for pr in self.pairs:
            ids = []
            for shape in (pr.a, pr.b):
                if id(shape) not in known:
                    c, r = bounding_spheres(shape)
                    start = len(radii)
                    centres += list(c @ shape.origin[:3, :3].T + shape.origin[:3, 3])
                    radii += list(r)
                    owner += [self.links.index(shape.link)] * len(r)
                    known[id(shape)] = range(start, len(radii))
                ids.append(known[id(shape)])
            combos.append([(u, v) for u in ids[0] for v in ids[1]])
        self._centres, self._radii = np.array(centres).reshape(-1, 3), np.array(radii)
        self._centres_h = np.concatenate([self._centres, np.ones((len(radii), 1))], 1)[:, None, :, None]
        self._owner = np.array(owner, int)
        width = max((len(c) for c in combos), default=0)
        self._sa = np.zeros((len(self.pairs), width), int)
        self._sb = np.zeros((len(self.pairs), width), int)
        self._pad = np.ones((len(self.pairs), width), bool)
        for i, c in enumerate(combos):
            self._sa[i, :len(c)] = [u for u, _ in c]
            self._sb[i, :len(c)] = [v for _, v in c]
            self._pad[i, :len(c)] = False
        self._origin_a = np.array([p.a.origin for p in self.pairs]).reshape(-1, 4, 4)
        self._origin_b = np.array([p.b.origin for p in self.pairs]).reshape(-1, 4, 4)
        self._req = coal.DistanceRequest()
        self._req.enable_signed_distance = True
        self._res = coal.DistanceResult()
        self._tf_a, self._tf_b = coal.Transform3s(), coal.Transform3s()

    def __len__(self) -> int:
        return len(self.pairs)

    def witnesses(self, poses: dict[str, np.ndarray], exact_below: float | None = None,
                  per_knot: int | None = None, always_below: float | None = None) -> Witnesses:
        """poses: link -> (knots, 4, 4) world poses. Separating plane for every pair and knot: from
        GJK/EPA where the sphere bound is under ``exact_below`` (default ``near``), else from the
        closest pair of covering spheres (a conservative plane and distance). ``per_knot`` caps the
        GJK calls per knot to the pairs with the smallest bounds; pairs bounded under
        ``always_below`` get GJK/EPA regardless of the cap."""
        P = len(self.pairs)
        K = next(iter(poses.values())).shape[0] if poses else 0
        if not P:
            z = np.zeros((0, K, 3))
            return Witnesses(z, z, z, np.zeros((0, K)), np.zeros((0, K), bool))
        link_T = np.stack([poses[name] for name in self.links])  # (L, K, 4, 4)
        Ts = link_T[self._owner]  # (spheres, K, 4, 4)
        world = np.matmul(Ts[..., :3, :], self._centres_h)[..., 0]  # (spheres, K, 3); matmul: 3x einsum's speed
        delta = world[self._sb] - world[self._sa]  # (P, width, K, 3)
        length = np.sqrt(np.einsum("...i,...i->...", delta, delta))
        gap = np.where(self._pad[..., None], np.inf, length - self._radii[self._sa][..., None]
                       - self._radii[self._sb][..., None])
        best = np.argmin(gap, axis=1)  # (P, K): the closest sphere combination per pair and knot
        pi, kk = np.arange(P)[:, None], np.arange(K)[None]
        dist = gap[pi, best, kk]
        d_len = length[pi, best, kk]
        n = delta[pi, best, kk] / np.maximum(d_len, 1e-9)[..., None]
        n[d_len < 1e-9] = (0.0, 0.0, 1.0)
        sa, sb = self._sa[pi, best], self._sb[pi, best]
        wa = world[sa, kk] + self._radii[sa][..., None] * n
        wb = world[sb, kk] - self._radii[sb][..., None] * n
        exact = np.zeros((P, K), bool)
        limit = self.near if exact_below is None else exact_below
        cand = dist < limit
        if per_knot is not None:  # only the per_knot closest candidates (by their bound) per knot
            rank = np.argsort(np.argsort(np.where(cand, dist, np.inf), axis=0), axis=0)
            cand &= rank < per_knot
        if always_below is not None:
            cand |= dist < always_below
        near = np.argwhere(cand)
        if len(near):
            ia, ka = near[:, 0], near[:, 1]
            Sa = link_T[self.link_a[ia], ka] @ self._origin_a[ia]
            Sb = link_T[self.link_b[ia], ka] @ self._origin_b[ia]
            res, ta, tb, req = self._res, self._tf_a, self._tf_b, self._req
            out_d, out_n, out_a, out_b = [], [], [], []
            for j, i in enumerate(ia.tolist()):
                ta.setRotation(Sa[j, :3, :3])
                ta.setTranslation(Sa[j, :3, 3])
                tb.setRotation(Sb[j, :3, :3])
                tb.setTranslation(Sb[j, :3, 3])
                res.clear()
                out_d.append(self.pairs[i].solver(ta, tb, req, res))
                out_n.append(res.normal)
                out_a.append(res.getNearestPoint1())
                out_b.append(res.getNearestPoint2())
            nn = np.array(out_n)
            norm = np.linalg.norm(nn, axis=1)
            good = np.isfinite(norm) & (norm > 0.5)  # degenerate (coincident shapes): keep the sphere plane
            ia, ka = ia[good], ka[good]
            n[ia, ka] = nn[good] / norm[good, None]
            dist[ia, ka] = np.array(out_d)[good]
            wa[ia, ka], wb[ia, ka] = np.array(out_a)[good], np.array(out_b)[good]
            exact[ia, ka] = True
        Ra, pa = link_T[self.link_a][..., :3, :3], link_T[self.link_a][..., :3, 3]
        Rb, pb = link_T[self.link_b][..., :3, :3], link_T[self.link_b][..., :3, 3]
        la = np.einsum("pkji,pkj->pki", Ra, wa - pa)
        lb = np.einsum("pkji,pkj->pki", Rb, wb - pb)
        return Witnesses(n, la, lb, dist, exact)
