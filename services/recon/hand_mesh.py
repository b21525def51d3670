"""A hand surface mesh posed from the 21 keypoints of the articulated hand model (pure).

The template is built once: a tapered tube along each finger's three bones, closed by a dome at
the tip, and a palm slab from the wrist to the finger bases. Every vertex is stored in the local
coordinates of what carries it (linear blend skinning): a finger vertex by its bone, its place
along the bone (0 at the bone's start, 1 at its end) and its offset from the bone's axis in the
bone's frame; a vertex on a joint ring by both bones meeting there, half each. A palm vertex by
its place on the palm (wrist to finger bases, little-finger edge to index edge) and its offset
along the palm's normal. Posing needs only the keypoints: each bone's frame is its parent's frame
turned by the smallest rotation onto the bone's direction (the fingers' frames start from the
palm's), so the mesh follows any person's bone lengths and any pose the fit produces.

Hand frame as in services/recon/hand_model.py: x toward the middle finger, z out of the back of
the hand, y toward the thumb on a right hand and away from it on a left one. A left hand's mesh is
the mirror image of a right hand's, so its triangles wind the other way (``faces(side)``).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache

import numpy as np

from services.recon.hand_model import CHAINS, palm_frame

AROUND = 12  # vertices per ring around a finger
RINGS_PER_BONE = 4  # rings from a bone's start (its joint) toward its end
TIP_RINGS = 3  # rings of the fingertip's dome, then its apex
PALM_ALONG = 10  # rings of the palm from the wrist to the finger bases
PALM_AROUND = 20  # vertices per palm ring (palmar half, then dorsal half)
PALM_HALF_THICKNESS = 0.013  # m
PALM_MARGIN = 0.4  # the palm reaches this fraction of a finger spacing beyond the index and little bases
WRIST_WIDTH = 0.8  # of the palm's width at the finger bases
# Tube radius (m) at each chain's base and tip (thumb, index, middle, ring, little).
RADIUS = np.array([[0.0125, 0.0085], [0.0095, 0.0072], [0.0098, 0.0074], [0.0092, 0.0070], [0.0082, 0.0064]])
PALM = -1  # ``Template.chain`` of a palm vertex


@dataclass(frozen=True)
class Template:
    """The rest-frame mesh: per-vertex skinning data and attributes, and the right hand's faces.

    Finger vertices (``chain`` 0-4): ``bone`` (0-2 along the chain), ``u`` along the bone, ``offset``
    in the bone's frame (x along the bone, y toward the thumb side, z toward the back of the hand),
    ``blend`` the weight of the previous bone's frame. Palm vertices (``chain`` -1): ``u`` from the
    wrist (0) to the finger bases (1), ``across`` from the little-finger edge (-1) to the index edge
    (+1), ``offset[2]`` along the palm's normal. ``angle``: a finger vertex's angle about its bone
    from the palmar direction (positive toward the thumb side), in radians."""

    chain: np.ndarray  # (N,) int
    bone: np.ndarray  # (N,) int
    u: np.ndarray  # (N,)
    offset: np.ndarray  # (N,3)
    blend: np.ndarray  # (N,)
    across: np.ndarray  # (N,)
    angle: np.ndarray  # (N,)
    right_faces: np.ndarray  # (F,3) int, counter-clockwise seen from outside on a right hand

    @property
    def n_vertices(self) -> int:
        return len(self.chain)

    def faces(self, side: str) -> np.ndarray:
        """Triangles wound counter-clockwise seen from outside for this hand (a left hand mirrors)."""
        return self.right_faces[:, ::-1].copy() if side == "left" else self.right_faces.copy()

    def along(self) -> np.ndarray:
        """A finger vertex's place along its chain: bone + u (0 at the chain's base, 3 at the tip)."""
        return self.bone + self.u


# Every ring's vertices run counter-clockwise about the axis from one ring to the next, so these
# triangles face outward on a right hand.
def _ring_faces(a: np.ndarray, b: np.ndarray) -> list[tuple[int, int, int]]:
    """The band between two rings of vertex ids (same length, closed), ring a before ring b."""
    n = len(a)
    out = []
    for k in range(n):
        k1 = (k + 1) % n
        out += [(a[k], b[k1], b[k]), (a[k], a[k1], b[k1])]
    return out


def _fan(centre: int, ring: np.ndarray, far: bool) -> list[tuple[int, int, int]]:
    """A cap closing a ring by a centre vertex beyond it (``far``) or before it."""
    n = len(ring)
    return [(centre, ring[k], ring[(k + 1) % n]) if far else (centre, ring[(k + 1) % n], ring[k]) for k in range(n)]


class _Builder:
    def __init__(self) -> None:
        self.cols: dict[str, list] = {k: [] for k in ("chain", "bone", "u", "offset", "blend", "across", "angle")}
        self.faces: list[tuple[int, int, int]] = []

    def add(self, chain: int, bone: int, u: float, offset: np.ndarray, blend: float = 0.0, across: float = 0.0,
            angle: float = 0.0) -> int:
        for k, v in zip(self.cols, (chain, bone, u, offset, blend, across, angle), strict=True):
            self.cols[k].append(v)
        return len(self.cols["chain"]) - 1

    def template(self) -> Template:
        c = self.cols
        return Template(np.array(c["chain"]), np.array(c["bone"]), np.array(c["u"], float),
                        np.array(c["offset"], float).reshape(-1, 3), np.array(c["blend"], float),
                        np.array(c["across"], float), np.array(c["angle"], float), np.array(self.faces, int))


def _finger(b: _Builder, chain: int) -> None:
    phi = 2 * np.pi * np.arange(AROUND) / AROUND - np.pi  # -pi..pi, 0 = palmar
    r0, r1 = RADIUS[chain]
    rings = []
    for bone in range(3):
        for k in range(RINGS_PER_BONE):
            u = k / RINGS_PER_BONE
            r = r0 + (r1 - r0) * (bone + u) / 3
            blend = 0.5 if (k == 0 and bone > 0) else 0.0  # a joint ring: half each bone
            ring = [b.add(chain, bone, u, [0.0, r * np.sin(p), -r * np.cos(p)], blend, angle=p) for p in phi]
            rings.append(np.array(ring))
    for k in range(TIP_RINGS + 1):  # the dome beyond the tip keypoint's ring
        a = np.pi / 2 * k / (TIP_RINGS + 1)
        r, ahead = r1 * np.cos(a), 0.8 * r1 * np.sin(a)
        rings.append(np.array([b.add(chain, 2, 1.0, [ahead, r * np.sin(p), -r * np.cos(p)], angle=p) for p in phi]))
    apex = b.add(chain, 2, 1.0, [0.8 * r1, 0.0, 0.0])
    for ra, rb in zip(rings[:-1], rings[1:], strict=False):
        b.faces += _ring_faces(ra, rb)
    b.faces += _fan(apex, rings[-1], far=True)
    b.faces += _fan(b.add(chain, 0, 0.0, [0.0, 0.0, 0.0]), rings[0], far=False)  # the base, hidden in the palm


def _palm(b: _Builder) -> None:
    psi = 2 * np.pi * (np.arange(PALM_AROUND) + 0.5) / PALM_AROUND  # (0, pi): dorsal; (pi, 2 pi): palmar
    rings = []
    for k in range(PALM_ALONG + 1):
        u = k / PALM_ALONG
        ring = [b.add(PALM, 0, u, [0.0, 0.0, PALM_HALF_THICKNESS * np.sin(p)], across=np.cos(p)) for p in psi]
        rings.append(np.array(ring))
    for ra, rb in zip(rings[:-1], rings[1:], strict=False):
        b.faces += _ring_faces(ra, rb)
    b.faces += _fan(b.add(PALM, 0, 0.0, [0.0, 0.0, 0.0]), rings[0], far=False)  # the wrist
    b.faces += _fan(b.add(PALM, 0, 1.0, [0.0, 0.0, 0.0]), rings[-1], far=True)  # under the fingers


@cache
def template() -> Template:
    """The hand template (built once). Its faces wind outward on a right hand; the tests check it."""
    b = _Builder()
    _palm(b)
    for chain in range(len(CHAINS)):
        _finger(b, chain)
    return b.template()


def _min_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Batched smallest rotations (n,3,3) turning unit vectors a (n,3) onto b (n,3)."""
    v = np.cross(a, b)
    c = np.einsum("ni,ni->n", a, b)
    K = np.zeros((len(a), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = v[:, 2], -v[:, 1], v[:, 0]
    scale = 1.0 / np.maximum(1.0 + c, 1e-6)  # a bone folded straight back (c = -1) stays unturned
    return np.eye(3)[None] + K + np.einsum("nij,njk->nik", K, K) * scale[:, None, None]


def bone_frames(keypoints: np.ndarray, side: str) -> tuple[np.ndarray, np.ndarray]:
    """The palm's frame (3,3) (columns x, thumb-side y, z out of the back of the hand) and each
    finger bone's frame (5,3,3,3) (chain, bone, then columns: along the bone, thumb side, back)."""
    R, _ = palm_frame(keypoints, side)
    R = R @ np.diag([1.0, -1.0 if side == "left" else 1.0, 1.0])  # y toward the thumb on either hand
    frames = np.empty((5, 3, 3, 3))
    prev = np.repeat(R[None], 5, axis=0)
    for j in range(3):
        d = keypoints[CHAINS[:, j + 1]] - keypoints[CHAINS[:, j]]
        n = np.linalg.norm(d, axis=1, keepdims=True)
        d = np.where(n > 1e-9, d / np.maximum(n, 1e-12), prev[:, :, 0])  # a zero-length bone keeps its parent's
        prev = np.einsum("nij,njk->nik", _min_rotation(prev[:, :, 0], d), prev)
        frames[:, j] = prev
    return R, frames


def _palm_edges(keypoints: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nodes of the palm's distal edge from the little-finger side to the index side (6,3), their
    places in [-1, 1] by arc length, and the wrist edge's half-width vector."""
    bases = keypoints[[17, 13, 9, 5]]
    ends = [bases[0] + PALM_MARGIN * (bases[0] - bases[1]), bases[-1] + PALM_MARGIN * (bases[-1] - bases[-2])]
    nodes = np.vstack([ends[0], bases, ends[1]])
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(nodes, axis=0), axis=1))])
    places = 2 * arc / max(arc[-1], 1e-9) - 1
    half = 0.5 * WRIST_WIDTH * np.linalg.norm(nodes[-1] - nodes[0]) * y
    return nodes, places, half


def pose(keypoints: np.ndarray, side: str, tmpl: Template | None = None) -> np.ndarray:
    """World vertices (N,3) of the template posed on keypoints (21,3) of a ``side`` hand."""
    t = tmpl or template()
    kp = np.asarray(keypoints, float)
    if kp.shape != (21, 3) or not np.isfinite(kp).all():
        raise ValueError(f"hand keypoints must be 21 finite 3-D points, got shape {kp.shape}")
    R, frames = bone_frames(kp, side)
    out = np.empty((t.n_vertices, 3))
    fing = t.chain >= 0
    c, j = t.chain[fing], t.bone[fing]
    start, end = kp[CHAINS[c, j]], kp[CHAINS[c, j + 1]]
    prev = frames[c, np.maximum(j - 1, 0)]
    F = (1 - t.blend[fing])[:, None, None] * frames[c, j] + t.blend[fing][:, None, None] * prev
    out[fing] = start + t.u[fing, None] * (end - start) + np.einsum("nij,nj->ni", F, t.offset[fing])
    palm = ~fing
    nodes, places, half = _palm_edges(kp, R[:, 1])
    a = t.across[palm]
    distal = np.stack([np.interp(a, places, nodes[:, k]) for k in range(3)], axis=1)
    wrist = kp[0] + a[:, None] * half
    u = t.u[palm, None]
    out[palm] = (1 - u) * wrist + u * distal + t.offset[palm, 2:3] * R[:, 2]
    return out
