"""The two worked examples: the tactile glove (thesis 4.8.1) and the fingertip sensor (4.6).

Glove: the base mesh is the project's hand model (services/recon/hand_mesh.py) posed on a relaxed
right hand of average size (services/recon/hand_model.py), each closed part (palm, five fingers)
smoothed by Loop subdivision. The sensors lie where the tactile projection
(services/recon/tactile_projection.py) reads them: a 2 x 6 sensor on the palmar half of each finger
(row 0 on the thumb's side, column 0 at the finger's base, column 5 at the tip keypoint; the thumb's
from its MCP joint), and the 6 x 6 palm sensor (row 0 at the wrist, column 0 on the little finger's
edge) with its 2 x 3 cutout between thumb and index. On the readout matrix (``GLOVE_ROWS``) the
palm has excitation lines 0-5 and each finger two of its own; all share reception lines 0-5. The
glove's cell map, written from this design, is the glove service's layout (services/glove/layout.py;
shipped in models/skin/glove_cellmap.json). Each carrier evaluates the hand model's own skinning at
the sensor's points, so the layout follows the hand however it is posed.

Fingertip: a 4 x 4 matrix whose rows and columns wrap around the tip at 45 degrees, one corner at
the tip, one at the base, two at the sides, on a capsule-shaped fingertip (trimesh).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from services.recon.hand_mesh import PALM, PALM_HALF_THICKNESS, RADIUS, Template, pose, template
from services.recon.hand_model import DEFAULT_BONES, DEFAULT_PALM, HandShape, local_points
from services.recon.tactile_projection import FINGERS, SENSOR_SPAN
from shared.demo import TACTILE_REGIONS
from skin.layout import Carrier, SensorSpec

MM = 1000.0  # the hand model is in metres, the skin tools in mm
RELAXED = np.array([0.0, 0.25, 0.3, 0.2])  # abduction, then flexion of the three joints (rad): a glove mold's pose
GLOVE_MATRIX = (16, 16)  # the readout module's excitation x reception lines
GLOVE_ROWS = {"palm": 0, "thumb": 6, "index": 8, "middle": 10, "ring": 12, "little": 14}  # first excitation line
PALM_CUTOUT = (4, 3, 2, 3)  # rows 4-5 x columns 3-5 of the palm's 6 x 6: the corner between thumb and index


@dataclass
class Design:
    """A worked example: its base mesh, and per sensor the spec, carrier and the base-mesh part it lies on."""

    name: str
    base: trimesh.Trimesh
    sensors: list[tuple[SensorSpec, Carrier, trimesh.Trimesh]]
    matrix: tuple[int, int]  # the readout matrix: excitation lines x reception lines
    regions: tuple[str, ...]  # region names; a cell map's region indices count in this order


def hand_keypoints(curl: np.ndarray = RELAXED) -> np.ndarray:
    """Right-hand keypoints (21,3) in the hand frame (m) of an average hand, every finger at ``curl``."""
    frames = np.repeat(np.eye(3)[None], 5, axis=0)
    x = np.array([0.6, 0.7, -0.4]) / np.linalg.norm([0.6, 0.7, -0.4])  # the thumb's base direction
    z = np.array([0.0, 0.0, 1.0]) - x[2] * x
    z /= np.linalg.norm(z)
    frames[0] = np.stack([x, np.cross(z, x), z], axis=1)
    shape = HandShape(DEFAULT_PALM.copy(), DEFAULT_BONES.copy(), frames)
    return local_points(shape, np.tile(curl, (5, 1)))


def _points(kp: np.ndarray, chain: np.ndarray, bone: np.ndarray, u: np.ndarray, offset: np.ndarray,
            blend: np.ndarray, across: np.ndarray) -> np.ndarray:
    """Points skinned by the hand model like its template's vertices (mm)."""
    n = len(chain)
    t = Template(chain, bone, u, offset, blend, across, np.zeros(n), np.zeros((0, 3), int))
    return pose(kp, "right", t) * MM


def finger_carrier(kp: np.ndarray, finger: str) -> Carrier:
    """A finger sensor's unit square on the palmar half of the finger's tube (s: thumb side -> the
    other side, t: base -> tip keypoint)."""
    chain = FINGERS.index(finger)
    a0, a1 = SENSOR_SPAN[finger]
    r0, r1 = RADIUS[chain]

    def carry(st: np.ndarray) -> np.ndarray:
        phi = np.pi / 2 - np.pi * st[:, 0]
        along = a0 + st[:, 1] * (a1 - a0)
        bone = np.minimum(np.floor(along), 2).astype(int)
        u = along - bone
        r = r0 + (r1 - r0) * along / 3
        offset = np.stack([np.zeros_like(r), r * np.sin(phi), -r * np.cos(phi)], axis=1)
        blend = np.where(bone > 0, 0.5 * np.clip(1 - 4 * u, 0, 1), 0.0)  # as the template's joint rings
        n = len(st)
        return _points(kp, np.full(n, chain), bone, u, offset, blend, np.zeros(n))

    return carry


def palm_carrier(kp: np.ndarray) -> Carrier:
    """The palm sensor's unit square on the palm's palmar face (s: wrist -> finger bases, t: little
    finger's edge -> index's edge)."""

    def carry(st: np.ndarray) -> np.ndarray:
        across = 2 * st[:, 1] - 1
        z = -PALM_HALF_THICKNESS * np.sqrt(np.clip(1 - across**2, 0, 1))
        offset = np.stack([np.zeros_like(z), np.zeros_like(z), z], axis=1)
        n = len(st)
        return _points(kp, np.full(n, PALM), np.zeros(n, int), st[:, 0], offset, np.zeros(n), across)

    return carry


def hand_base_mesh(kp: np.ndarray, subdivisions: int = 2) -> tuple[trimesh.Trimesh, dict[str, trimesh.Trimesh]]:
    """The hand model's surface posed on ``kp`` (mm), each closed part Loop-subdivided; also each part
    on its own (the surface its sensor is projected onto)."""
    t = template()
    verts = pose(kp, "right") * MM
    owner = t.chain[t.right_faces[:, 0]]
    parts = {}
    for chain, name in [(PALM, "palm")] + list(enumerate(FINGERS)):
        faces = t.right_faces[owner == chain]
        used, inv = np.unique(faces, return_inverse=True)
        v, f = trimesh.remesh.subdivide_loop(verts[used], inv.reshape(-1, 3), iterations=subdivisions)
        parts[name] = trimesh.Trimesh(v, f, process=False)
    return trimesh.util.concatenate(list(parts.values())), parts


def glove(curl: np.ndarray = RELAXED, palm_cutouts: tuple[tuple[int, int, int, int], ...] = (PALM_CUTOUT,)) -> Design:
    """The glove: five finger sensors and the palm sensor on the posed hand model (``palm_cutouts``:
    (row, col, rows, cols) blocks left out of the palm's 6 x 6)."""
    kp = hand_keypoints(curl)
    base, parts = hand_base_mesh(kp)
    sensors = [(SensorSpec("palm", "palm", 6, 6, GLOVE_ROWS["palm"], 0, tuple(tuple(c) for c in palm_cutouts),
                           gap=1.0, cable_length=40.0), palm_carrier(kp), parts["palm"])]
    for finger in FINGERS:
        spec = SensorSpec(finger, finger, 2, 6, GLOVE_ROWS[finger], 0, gap=1.0, cable_length=60.0)
        sensors.append((spec, finger_carrier(kp, finger), parts[finger]))
    return Design("glove", base, sensors, GLOVE_MATRIX, TACTILE_REGIONS)


FINGERTIP_RADIUS = 8.0  # mm
FINGERTIP_LENGTH = 30.0  # mm of cylinder below the dome


def fingertip(pitch: float = 4.5) -> Design:
    """A 4 x 4 fingertip sensor at 45 degrees on a capsule fingertip (axis z, tip at +z, palmar -y)."""
    R, h = FINGERTIP_RADIUS, FINGERTIP_LENGTH
    base = trimesh.creation.capsule(height=h, radius=R, count=[48, 48])
    side = 4 * pitch
    reach = 0.85 * R * np.pi / 2  # the tip corner stops short of the apex, where meridians meet

    def carry(st: np.ndarray) -> np.ndarray:
        p, q = (st[:, 0] - 0.5) * side, (st[:, 1] - 0.5) * side
        along = (p + q) / np.sqrt(2) + reach - side / np.sqrt(2)  # from the dome's start, + toward the tip
        phi = (q - p) / np.sqrt(2) / R
        theta = np.clip(along, 0, None) / R  # over the dome, along its meridians
        rho = np.where(along > 0, R * np.cos(theta), R)
        z = h / 2 + np.where(along > 0, R * np.sin(theta), along)
        return np.stack([rho * np.sin(phi), -rho * np.cos(phi), z], axis=1)

    spec = SensorSpec("fingertip", "fingertip", 4, 4, 0, 0, gap=0.8, subdiv=6, cable_length=50.0)
    return Design("fingertip", base, [(spec, carry, base)], (4, 4), ("fingertip",))
