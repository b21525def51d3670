"""Tactile projection (thesis 5.7): the glove's readout matrix sampled onto the hand mesh (pure).

Every vertex of the hand template (services/recon/hand_mesh.py) that a sensor covers carries a
(row, col) coordinate into the 16x16 readout matrix, following the glove's layout: its cell map
file (services/glove/layout.py; recon's ``cellmap`` parameter, by default the shipped
models/skin/glove_cellmap.json) says which block of the matrix each sensor occupies and which of
its crossings hold no cell. Where each sensor lies on the hand:

- a finger sensor (2 rows across x 6 columns along) lies on the palmar half of its finger's tube:
  its first column at the finger's base, its last at the tip (two columns per phalanx; the thumb's
  sensor runs from its MCP joint to the tip, three columns per phalanx), its first row on the thumb's
  side;
- the palm sensor lies on the palm's palmar face: its first row at the wrist, its last at the finger
  bases, its first column on the little finger's edge, its last on the index's; so the shipped 2x3
  cutout (rows 4-5, columns 3-5) is the corner between thumb and index. Vertices over a cutout
  sense nothing.

Sampling is bicubic (cubic B-spline interpolation, ``scipy.ndimage.map_coordinates`` of order 3).
Padding keeps sensors apart: each sensor is sampled from its own copy of the matrix in which every
other crossing (another sensor's cell, an unpopulated crossing, an unused line) holds the value of
the sensor's nearest cell, so no vertex reads a neighbouring sensor or a dead line.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.ndimage import distance_transform_edt, map_coordinates

from services.glove import layout as glove_layout
from services.glove.layout import COLS, ROWS, Layout
from services.recon.hand_mesh import PALM, Template, pose, template
from shared import msgs
from shared.demo import TACTILE_REGIONS

MSGTYPE = "xm_msgs/msg/TactileMesh"
FINGERS = ("thumb", "index", "middle", "ring", "little")  # the hand model's chain order
# Where each finger's sensor lies along its chain (bone + fraction: 0 at the base, 3 at the tip).
SENSOR_SPAN = {"thumb": (1.0, 3.0), "index": (0.0, 3.0), "middle": (0.0, 3.0), "ring": (0.0, 3.0),
               "little": (0.0, 3.0)}


def vertex_coordinates(tmpl: Template, layout: Layout) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per vertex: (row, col) in the readout matrix (N,2), the sensor's region index (N,) (-1: none)
    and whether a sensor cell covers it (N,) bool."""
    n = tmpl.n_vertices
    rc = np.zeros((n, 2))
    region = np.full(n, -1)
    sensed = np.zeros(n, bool)

    def place(sel: np.ndarray, k: int, rows: np.ndarray, cols: np.ndarray) -> None:
        """Vertices ``sel`` on sensor k at fractional rows and cols (the sensor's block spans 0..1)."""
        s = layout.sensors[TACTILE_REGIONS[k]]
        r0, nr, c0, nc = s.row0, s.rows, s.col0, s.cols
        rc[sel] = np.stack([r0 - 0.5 + nr * rows, c0 - 0.5 + nc * cols], axis=1)
        cell = np.clip(np.rint(rc[sel]).astype(int), [r0, c0], [r0 + nr - 1, c0 + nc - 1])
        # The nearest crossing must hold a cell of this sensor (a cutout's do not).
        ok = layout.region[cell[:, 0], cell[:, 1]] == k
        idx = np.flatnonzero(sel)[ok]
        region[idx], sensed[idx] = k, True

    along = tmpl.along()
    for chain, name in enumerate(FINGERS):
        k = TACTILE_REGIONS.index(name)
        a0, a1 = SENSOR_SPAN[name]
        sel = (tmpl.chain == chain) & (np.abs(tmpl.angle) <= np.pi / 2) & (along >= a0) \
            & (np.linalg.norm(tmpl.offset, axis=1) > 0)  # not the centre closing the tube's base
        place(sel, k, (np.pi / 2 - tmpl.angle[sel]) / np.pi, (np.minimum(along[sel], a1) - a0) / (a1 - a0))
    sel = (tmpl.chain == PALM) & (tmpl.offset[:, 2] < 0)
    place(sel, TACTILE_REGIONS.index("palm"), tmpl.u[sel], (tmpl.across[sel] + 1) / 2)
    return rc, region, sensed


def padding_indices(layout: Layout, region: int) -> np.ndarray:
    """(2,ROWS,COLS) for every crossing the row and column of the sensor's nearest cell."""
    _, idx = distance_transform_edt(layout.region != region, return_indices=True)
    return idx


class TactileProjector:
    """The template's tactile coordinates and padding for a glove layout (None: the shipped cell
    map), computed once; per frame, pose and sample."""

    def __init__(self, tmpl: Template | None = None, layout: Layout | None = None) -> None:
        self.template = tmpl or template()
        self.layout = layout or glove_layout.default()
        self.rc, self.region, self.sensed = vertex_coordinates(self.template, self.layout)
        # Per sensor: its vertices, their (row, col) and the padding of its copy of the matrix.
        self.sensors = [(np.flatnonzero(self.region == k), self.rc[self.region == k].T,
                         padding_indices(self.layout, k))
                        for k in np.unique(self.region[self.sensed])]

    def sample(self, pressure: np.ndarray) -> np.ndarray:
        """Per-vertex pressure (N,) float32 from a ROWS x COLS frame (kPa); 0 where nothing senses."""
        p = np.asarray(pressure, float)
        if p.size != ROWS * COLS:
            raise ValueError(f"tactile frame has {p.size} values, expected {ROWS}x{COLS}")
        p = p.reshape(ROWS, COLS)
        if not np.isfinite(p).all():
            raise ValueError("tactile frame has non-finite values")
        out = np.zeros(self.template.n_vertices, np.float32)
        for vertices, coords, pad in self.sensors:
            out[vertices] = map_coordinates(p[pad[0], pad[1]], coords, order=3, mode="nearest")
        return out

    def hand(self, keypoints: np.ndarray, side: str, pressure: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One hand: posed vertices (N,3), its faces (F,3) and per-vertex pressure (N,)."""
        return pose(keypoints, side, self.template), self.template.faces(side), self.sample(pressure)

    def message(self, stamp: float, hand_names: list[str], hands: np.ndarray, hand_mask: np.ndarray,
                pressures: dict[str, np.ndarray]) -> tuple[Any, dict[str, str]]:
        """The TactileMesh of every hand with a glove frame in ``pressures`` and all 21 keypoints
        (a message of no hands when there is none: the key keeps the frame sets' pace, and a
        consumer knows the meshes are gone), and why each other gloved hand was left out."""
        names, verts, faces, values, skipped = [], [], [], [], {}
        for i, name in enumerate(hand_names):
            if name not in pressures:
                continue
            if not np.asarray(hand_mask[i], bool).all():
                skipped[name] = "incomplete_hand"  # no surface to pose without every keypoint
                continue
            try:
                v, f, p = self.hand(hands[i], name, pressures[name])
            except ValueError:
                skipped[name] = "bad_input"  # a glove frame of the wrong size, non-finite values
                continue
            names.append(name)
            verts.append(v)
            faces.append(f)
            values.append(p)
        if not names:
            n = self.template.n_vertices
            return tactile_mesh_message(stamp, [], np.zeros((0, n, 3)), np.zeros((0, 0, 3)), np.zeros((0, n)),
                                        self.sensed), skipped
        return tactile_mesh_message(stamp, names, np.stack(verts), np.stack(faces), np.stack(values),
                                    self.sensed), skipped

def tactile_mesh_message(stamp: float, hand_names: list[str], vertices: np.ndarray, faces: np.ndarray,
                         pressure: np.ndarray, sensed: np.ndarray) -> Any:
    """An xm_msgs/msg/TactileMesh: vertices (H,N,3), faces (H,F,3), pressure (H,N), sensed (N,)."""
    return msgs.make(MSGTYPE, header=msgs.header(stamp, "world"), hand_names=list(hand_names),
                     vertex_count=int(vertices.shape[1]), vertices=np.asarray(vertices, np.float32).ravel(),
                     faces=np.asarray(faces, np.uint32).ravel(), pressure=np.asarray(pressure, np.float32).ravel(),
                     sensed=np.asarray(sensed, np.uint8).ravel())

