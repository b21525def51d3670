"""Wiping (thesis 7.6.2): a sponge is grasped, lifted, pressed onto a marked area of a plate and
wiped across it in circles at a target pressure.

The sponge is a foam pad under a rigid handle; the teacher pinches the handle. Its keypoints sit
on the handle and the pad's top face, so pressing lowers them by the foam's compression
(force / ``SPONGE_N_PER_M``, millimetres): the pad's own face (keypoint ``bottom``, rigid with
the handle) then lies that far below the plate's surface. The glove reads the pressing force on
the middle, ring and palm regions; thumb and index hold the handle.

Success (``outcome``): at least ``COVERED_FRACTION`` of the marked area was under the pad while
the pad pressed with a force inside ``FORCE_BAND_N``. The positions alone give the force only
through millimetres of foam compression; the glove reads it directly.
"""

from __future__ import annotations

import numpy as np

from services.world.tracks import Track, rot_z

PAD_HALF = (0.030, 0.020, 0.012)  # foam pad half extents (m)
HANDLE_TOP = 0.040  # handle top above the pad's face
GRIP_Z = 0.032  # pinch point on the handle above the pad's face
PLATE_HALF = (0.070, 0.050, 0.0025)
PLATE_TOP = 2 * PLATE_HALF[2]
AREA_HALF = (0.040, 0.025)  # the marked area, centred on the plate
SPONGE_N_PER_M = 2000.0  # foam stiffness: 6 N compresses it 3 mm
FORCE_BAND_N = (4.0, 9.0)  # pressure that wipes: less smears, more squeezes the sponge dry
TARGET_FORCE_N = (5.5, 7.0)  # the teacher's press, drawn per demonstration
FOOTPRINT_M = 0.02  # radius of the disc inscribed in the pad: the part sure to touch
COVERED_FRACTION = 0.9
GRIP_FORCE_N = 2.0
PRESS_SHARE = {"middle": 0.3, "ring": 0.2, "palm": 0.5}  # how the glove's regions share the press
GRID = (9, 6)  # test points over the marked area

OBJECT_POINTS = {
    "sponge": {"handle": (0.0, 0.0, HANDLE_TOP), "c0": (-PAD_HALF[0], -PAD_HALF[1], 2 * PAD_HALF[2]),
               "c1": (PAD_HALF[0], PAD_HALF[1], 2 * PAD_HALF[2]), "c2": (PAD_HALF[0], -PAD_HALF[1], 2 * PAD_HALF[2]),
               "bottom": (0.0, 0.0, 0.0)},
    "plate": {"center": (0.0, 0.0, PLATE_TOP), "a0": (-AREA_HALF[0], -AREA_HALF[1], PLATE_TOP),
              "a1": (AREA_HALF[0], -AREA_HALF[1], PLATE_TOP), "a2": (AREA_HALF[0], AREA_HALF[1], PLATE_TOP),
              "a3": (-AREA_HALF[0], AREA_HALF[1], PLATE_TOP)},
}
GEOMS = {  # MuJoCo bodies, as services/world/model.py lists them
    "sponge": [("box", PAD_HALF, (0.0, 0.0, PAD_HALF[2]), (0.95, 0.85, 0.2, 1), 0.01),
               ("box", (0.010, 0.015, 0.008), (0.0, 0.0, 2 * PAD_HALF[2] + 0.008), (0.2, 0.4, 0.8, 1), 0.01)],
    "plate": [("box", PLATE_HALF, (0.0, 0.0, PLATE_HALF[2]), (0.85, 0.85, 0.85, 1), 0.3),
              ("box", (*AREA_HALF, 0.0003), (0.0, 0.0, PLATE_TOP + 0.0003), (0.6, 0.3, 0.3, 1), 0.001)],
}


def sample_layout(rng: np.random.Generator) -> dict:
    return {"sponge": [rng.uniform(-0.08, 0.08), rng.uniform(0.06, 0.14), rng.uniform(-0.5, 0.5)],
            "plate": [rng.uniform(-0.06, 0.08), rng.uniform(-0.13, -0.05), rng.uniform(-0.4, 0.4)],
            "force_n": float(rng.uniform(*TARGET_FORCE_N))}


class WipePath:
    """The pinch point while wiping: the circles' path in the plate's plane, lowered by the foam's
    compression under the force track."""

    def __init__(self, moves: Track, force: Track, contact: tuple[float, float]) -> None:
        self.moves, self.force, self.contact = moves, force, contact

    def __call__(self, t: float) -> np.ndarray:
        p = self.moves(t).copy()
        if self.contact[0] <= t <= self.contact[1]:
            p[2] -= float(self.force(t)[0]) / SPONGE_N_PER_M
        return p


def build(teacher, rng: np.random.Generator, T, jitter, start_g: np.ndarray, start_p: np.ndarray,
          pinch_square: float) -> None:
    """Sets the wiping script's tracks and timing on ``teacher`` (services/world/teacher.Teacher)."""
    sx, sy, syaw = teacher.layout["sponge"]
    px, py, pyaw = teacher.layout["plate"]
    force_n = teacher.layout["force_n"]
    grip0 = np.array([sx, sy, GRIP_Z])
    plate0 = np.array([px, py, 0.0])
    contact_z = PLATE_TOP + GRIP_Z  # the pinch with the pad just touching the plate
    R = rot_z(pyaw)
    # circles along the area's long axis, there and back: the pad's disc sweeps the whole area
    n_loops, radius = 6, 0.012
    t0, t1 = T(5.0), T(9.0)
    moves = (Track().add(0, start_g).hold(T(0.5)).add(T(1.8), grip0 + [0, 0, 0.05] + jitter(0.003))
             .add(T(2.3), grip0).hold(T(2.7)).add(T(3.3), grip0 + [0, 0, 0.08]))
    lane = AREA_HALF[0] - 0.012
    start = plate0 + R @ [-lane, 0.0, 0.0]
    moves.add(T(4.3), start + [radius * np.cos(pyaw), radius * np.sin(pyaw), contact_z + 0.03])
    moves.add(T(4.9), start + [*(R @ [radius, 0.0, 0.0])[:2], contact_z])
    for k in range(1, 121):
        s = k / 120
        along = -lane + 2 * lane * (1 - abs(1 - 2 * s))  # there and back
        ang = 2 * np.pi * n_loops * s
        local = [along + radius * np.cos(ang), radius * np.sin(ang), 0.0]
        moves.add(t0 + (t1 - t0) * s, plate0 + R @ local + [0, 0, contact_z])
    moves.hold(T(9.3)).add(T(9.9), moves.values[-1] + [0, 0, 0.08]).hold(T(10.5))
    wobble = rng.uniform(0.2, 0.5)
    force = Track().add(0, 0.0).hold(T(4.8)).add(T(5.0), force_n)
    for k in range(1, 9):  # a human's press wavers
        force.add(t0 + (t1 - t0) * k / 8, force_n + wobble * (-1) ** k)
    force.add(T(9.3), 0.0).hold(T(10.5))
    contact = (T(4.8), T(9.3))
    teacher.pinch = WipePath(moves, force, contact)
    teacher.tip = Track().add(0, start_p).hold(T(10.5))  # the other hand rests
    teacher.press_force = force
    teacher.contact_window = contact
    teacher.pinch_yaw = Track().add(0, 0.0).hold(T(0.5)).add(T(2.0), syaw + pinch_square).hold(T(10.5))
    teacher.press_yaw = Track().add(0, 0.0).hold(T(10.5))
    teacher.aperture = Track().add(0, 0.05).hold(T(2.0)).add(T(2.5), 0.03).add(T(2.7), 0.021).hold(T(10.5))
    teacher.opposition = Track().add(0, 0.3).add(T(1.8), 1.0).hold(T(10.5))
    teacher.phases = [(0.0, "approach"), (T(2.3), "grasp"), (T(3.0), "transport"), (T(4.8), "wipe"),
                      (T(9.3), "lift"), (T(10.0), "done")]
    teacher.grasp_window = (T(2.7), np.inf)
    teacher.press_window = (np.inf, np.inf)
    teacher.insert_time = np.inf
    teacher.grip0, teacher.syaw, teacher.plate0, teacher.pyaw = grip0, syaw, plate0, pyaw
    teacher.duration = T(10.5)


def objects(teacher, t: float, pinch_now: np.ndarray) -> dict[str, tuple[np.ndarray, float]]:
    """Sponge rigid to the pinch once grasped, plate still."""
    if t >= teacher.grasp_window[0]:
        turn = float(teacher.pinch_yaw(t)[0]) - float(teacher.pinch_yaw(teacher.grasp_window[0])[0])
        sponge = (pinch_now - [0, 0, GRIP_Z], teacher.syaw + turn)
    else:
        sponge = (teacher.grip0 - [0, 0, GRIP_Z], teacher.syaw)
    return {"sponge": sponge, "plate": (teacher.plate0.copy(), teacher.pyaw)}


def forces(teacher, t: float, regions: tuple[str, ...], grasp: int) -> np.ndarray:
    """(2,R) N: the grip on thumb and index, the press shared by middle, ring and palm."""
    out = np.zeros((2, len(regions)))
    g0 = teacher.grasp_window[0]
    if t >= g0 - 0.3:
        grip = GRIP_FORCE_N * min(1.0, (t - (g0 - 0.3)) / 0.3)
        out[grasp, regions.index("thumb")] = out[grasp, regions.index("index")] = grip
    press = float(teacher.press_force(t)[0])
    for region, share in PRESS_SHARE.items():
        out[grasp, regions.index(region)] = share * press
    return out


# --- the success test ------------------------------------------------------------------------
def press_from_tactile(hands: np.ndarray, objects: np.ndarray, names: list[str], tactile: np.ndarray,
                       kpa_per_n: float, regions: tuple[str, ...]) -> np.ndarray:
    """(T,) N pressed, from the (T,2,R) kPa of the hand holding the sponge (its pinch closest to the
    handle at each step): its press regions."""
    pinch = 0.5 * (hands[:, :, 4] + hands[:, :, 8])
    handle = objects[:, names.index("sponge/handle")] - [0, 0, HANDLE_TOP - GRIP_Z]
    near = np.argmin(np.linalg.norm(pinch - handle[:, None], axis=-1), axis=1)
    idx = [regions.index(r) for r in PRESS_SHARE]
    return tactile[np.arange(len(hands)), near][:, idx].sum(axis=-1) / kpa_per_n


def compression(objects: np.ndarray, names: list[str]) -> np.ndarray:
    """(T,) m the pad's face lies below the plate's surface (negative: above it; -inf where the pad
    is not over the plate)."""
    center = objects[:, names.index("plate/center")]
    pad = objects[:, names.index("sponge/bottom")]
    ex = objects[:, names.index("plate/a1")] - objects[:, names.index("plate/a0")]
    ey = objects[:, names.index("plate/a3")] - objects[:, names.index("plate/a0")]
    rel = pad - center
    u = np.abs((rel * ex).sum(-1)) / np.maximum(np.linalg.norm(ex, axis=-1), 1e-9)
    v = np.abs((rel * ey).sum(-1)) / np.maximum(np.linalg.norm(ey, axis=-1), 1e-9)
    over = (u <= PLATE_HALF[0]) & (v <= PLATE_HALF[1])
    return np.where(over, center[:, 2] - pad[:, 2], -np.inf)


def press_from_positions(objects: np.ndarray, names: list[str]) -> np.ndarray:
    """(T,) N a position-controlled robot would press with, following these keypoints: the foam's
    compression times its stiffness."""
    return SPONGE_N_PER_M * np.clip(compression(objects, names), 0.0, None)


def area_points(objects_t: np.ndarray, names: list[str]) -> np.ndarray:
    """(G,3) test points over the marked area at one time step, from its corner keypoints."""
    a0, a1, a3 = (objects_t[names.index(f"plate/a{i}")] for i in (0, 1, 3))
    u = (np.arange(GRID[0]) + 0.5) / GRID[0]
    v = (np.arange(GRID[1]) + 0.5) / GRID[1]
    uu, vv = np.meshgrid(u, v, indexing="ij")
    return a0 + uu.reshape(-1, 1) * (a1 - a0) + vv.reshape(-1, 1) * (a3 - a0)


def outcome(objects: np.ndarray, names: list[str], force_n: np.ndarray, contact_m: float = 0.0) -> dict:
    """The world's success test over a trajectory: objects (T,K,3), force_n (T,) N pressed.

    A test point of the marked area is wiped when the pad's footprint is over it at a step whose
    force lies inside FORCE_BAND_N, with the pad's face within ``contact_m`` of the plate (0: in
    contact; a force-controlled robot closes a few millimetres itself). Returns coverage (fraction
    wiped), in_band (fraction of contact steps inside the band), peak force and success."""
    lo, hi = FORCE_BAND_N
    comp = compression(objects, names)
    touching = comp >= -contact_m
    in_band = touching & (force_n >= lo) & (force_n <= hi)
    covered = np.zeros(GRID[0] * GRID[1], bool)
    pad = objects[:, names.index("sponge/bottom"), :2]
    for t in np.flatnonzero(in_band):
        pts = area_points(objects[t], names)[:, :2]
        covered |= np.linalg.norm(pts - pad[t], axis=1) <= FOOTPRINT_M
    contact_steps = touching & (force_n > 0.5)
    coverage = float(covered.mean())
    return {"coverage": coverage, "in_band": float(in_band.sum() / max(contact_steps.sum(), 1)),
            "peak_force_n": float(force_n.max(initial=0.0)), "success": bool(coverage >= COVERED_FRACTION)}


class WipeMonitor:
    """The success test in the physical world (robot mode): fed the object keypoints and the pad's
    measured contact force step by step, it keeps which test points of the marked area were wiped."""

    def __init__(self) -> None:
        self.covered = np.zeros(GRID[0] * GRID[1], bool)
        self.peak_force_n = 0.0

    def update(self, objects_t: np.ndarray, names: list[str], force_n: float) -> None:
        self.peak_force_n = max(self.peak_force_n, float(force_n))
        if not FORCE_BAND_N[0] <= force_n <= FORCE_BAND_N[1]:
            return
        pts = area_points(objects_t, names)[:, :2]
        pad = objects_t[names.index("sponge/bottom"), :2]
        self.covered |= np.linalg.norm(pts - pad, axis=1) <= FOOTPRINT_M

    def result(self) -> dict:
        coverage = float(self.covered.mean())
        return {"coverage": coverage, "peak_force_n": self.peak_force_n, "success": coverage >= COVERED_FRACTION}
