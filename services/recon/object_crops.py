"""Per-object crops for the detector's object stage (pure).

In a readout window the network's first stage sees the board at about 7 input pixels across and
the camera module at about 3, so its object peaks land on a neighbouring keypoint of the same object
(the board's corners) or a few pixels off, 4 px median in the window (about 2 cm at the rig's
0.9 m). The object stage looks at one object at a time at the window's own resolution, upsampled:
each object's 3-D centre is the median of its confident first-stage peaks per view, triangulated
with a coarse gate (the median of an object's peaks does not move when the first stage exchanges
two of its keypoints), projected back into every view; the crop around it spans a fixed metric
size at that depth. No mirroring: the board's corners are told apart by their handedness.

Cost (the P6 budget): an object is cropped only in its best views (``view_scores``: the largest
projection of its last keypoints, inside the window, least covered by a hand in front of it;
``choose_views`` keeps the top ``VIEWS``), and a resting object's detections are reused on every
other frame set (``ObjectSchedule``: an object whose first-stage centre stays within ``REST_M``
of where it was at its last refresh rests; at most one resting object is refreshed per frame set,
the stalest first; an object a hand is near is cropped every frame set). Every crop of a frame set
goes through the network in one batch.

A crop whose centre misses its object still gets confident peaks on whatever it shows, at about the
same place in every view (the views' crops are centred on one wrong 3-D point), so they triangulate.
Such peaks follow the crop: a crop that is not clearly on its object is checked by a twin shifted
by a fraction of its side (``disagreement``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.recon.triangulation import project, triangulate_robust

HALF_SIZE_M = 0.05  # half the crop's side at the object's depth: the board's half diagonal (34 mm) plus slack
MIN_PEAKS = 2  # confident first-stage peaks of an object needed in a view for its centre there
CENTRE_GATE_PX = 12.0  # reprojection gate of the centre's triangulation (the medians are coarse)
VIEWS = 3  # views cropped per object: two triangulate, a third lets the triangulation reject one
REST_M = 0.015  # an object whose first-stage centre moved less than this since its last refresh rests
MAX_AGE = 1  # frame sets a resting object's detections are reused before it is cropped again
RESTING_PER_SET = 1  # resting objects refreshed per frame set, the stalest first
EXTENT_M = 0.03  # an object's radius when its keypoints are not known yet (the board's half diagonal: 34 mm)
HAND_RADIUS_M = 0.06  # a hand's radius as an occluder, around its centre (palm and curled fingers)
IN_FRONT_M = 0.03  # a hand whose centre is at most this behind the object's still covers it (it holds it)
MIN_VISIBLE = 0.05  # an object fully behind a hand still ranks its views by size
# A crop whose peaks of its own object's keypoints have a lower mean confidence missed the object
# (the first stage's centre of it was off by about a half side or more) and says nothing of it.
# Chosen on validation sessions 7311 and 7313 (bench/recon.py --object-present-confidence).
PRESENT_CONFIDENCE = 0.6
MIN_EXTENT_M = 0.005  # triangulated keypoints closer than this to their mean say nothing of the object's extent
# A crop that passes PRESENT_CONFIDENCE but not TRUSTED is cropped again VERIFY_SHIFT half sides
# off (diagonally): peaks on the object stay where they are in the image, peaks the network puts on
# whatever a crop that missed shows follow the crop. More than VERIFY_PX apart: dropped. All chosen
# on validation sessions 7311 and 7313 (bench/recon.py --object-verify-shift).
TRUSTED = 0.8  # on sessions 7311 and 7313, 1 of 204 crops this confident had its peaks over 3 px off
VERIFY_SHIFT = 0.3  # 0.21 half sides per axis: 1.4 standard deviations of the training crops' jitter
VERIFY_PX = 1.0  # full-image pixels, median over the keypoints confident in both crops
PEAK_CONFIDENCE = 0.3  # a peak this confident places its keypoint
# A hand this near an object's first-stage centre may be moving it: the object is cropped on every
# frame set rather than resting (a held board can move 2 cm between frame sets while its first-stage
# centre, placed from 7 input pixels, moves less than REST_M).
BUSY_M = 0.10
# An object no hand is near stays where it was placed when the first stage misses it or puts it
# farther than this away: in a full frame (camhub's reacquisition, every 10th frame set) the first
# stage sees the camera module at about 1 input pixel and put it 13 cm off, so the crop there missed.
JUMP_M = 0.05


def object_slices(names: list[str], first: int) -> list[tuple[str, slice]]:
    """(object, rows) of the keypoints named ``object/point`` from row ``first`` on, in order."""
    out: list[tuple[str, slice]] = []
    for i, n in enumerate(names[first:], start=first):
        obj = n.split("/")[0]
        if out and out[-1][0] == obj:
            out[-1] = (obj, slice(out[-1][1].start, i + 1))
        else:
            out.append((obj, slice(i, i + 1)))
    return out


def object_centres(P: np.ndarray, uv: np.ndarray, conf: np.ndarray, objects: list[slice],
                   threshold: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    """Each object's 3-D centre from the first stage's peaks: P (C,3,4), uv (C,N,2) full-image
    pixels, conf (C,N). Returns centres (O,3) and a mask (O,) of the objects found in two views or more."""
    C = len(P)
    med = np.zeros((C, len(objects), 2))
    seen = np.zeros((C, len(objects)), bool)
    for o, sl in enumerate(objects):
        for c in range(C):
            ok = conf[c, sl] >= threshold
            if ok.sum() >= min(MIN_PEAKS, sl.stop - sl.start):
                med[c, o] = np.median(uv[c, sl][ok], axis=0)
                seen[c, o] = True
    points, mask, _ = triangulate_robust(P, med, seen.astype(float), gate_px=CENTRE_GATE_PX)
    return points, mask.astype(bool)


def disagreement(uv_a: np.ndarray, conf_a: np.ndarray, uv_b: np.ndarray, conf_b: np.ndarray,
                 threshold: float = PEAK_CONFIDENCE) -> float:
    """The median distance (pixels) between two crops' peaks (k,2) of one object's keypoints, over
    those confident in both; inf when none is."""
    ok = (np.asarray(conf_a) >= threshold) & (np.asarray(conf_b) >= threshold)
    if not ok.any():
        return float("inf")
    return float(np.median(np.linalg.norm(np.asarray(uv_a, float)[ok] - np.asarray(uv_b, float)[ok], axis=1)))


def view_scores(P: np.ndarray, focal: np.ndarray, windows: np.ndarray, centres: np.ndarray, wanted: np.ndarray,
                keypoints: list[np.ndarray | None], hands: np.ndarray | None = None,
                hands_found: np.ndarray | None = None) -> np.ndarray:
    """How well each view shows each object, (C,O): 0 where the object's centre is outside the
    view's window (C,4: x, y, width, height), behind the camera or not ``wanted`` (O,); else the
    object's radius in pixels (from its last 3-D ``keypoints`` (k,3) projected, so a board seen
    edge-on ranks low; ``EXTENT_M`` at its depth where they are unknown) times the share of it no
    hand in front covers (``hands`` (H,3) centres, ``hands_found`` (H,); a disc overlap along the
    line between the two projections)."""
    C, O = len(P), len(centres)
    axis = np.linalg.norm(P[:, 2, :3], axis=-1)[:, None]  # P's third row, scaled: depth along the optical axis
    pix, z = project(P, centres)
    depth = z / axis
    x0, y0, w, h = (np.asarray(windows, float)[:, i:i + 1] for i in range(4))
    inside = (np.asarray(wanted, bool)[None, :] & (depth > 0.05) & (pix[..., 0] >= x0) & (pix[..., 0] < x0 + w)
              & (pix[..., 1] >= y0) & (pix[..., 1] < y0 + h))
    safe = np.where(depth > 0.05, depth, 1.0)
    radius = focal[:, None] * EXTENT_M / safe
    for o, kp in enumerate(keypoints):
        if kp is not None and len(kp) >= 2:
            kpix, _ = project(P, np.asarray(kp, float))  # (C,k,2)
            spread = np.sqrt(((kpix - kpix.mean(axis=1, keepdims=True)) ** 2).sum(-1).mean(-1))
            # a disc's RMS radius is its radius over sqrt(2); an edge-on view keeps a floor so it still ranks
            radius[:, o] = np.maximum(np.sqrt(2.0) * spread, 0.25 * radius[:, o])
    visible = np.ones((C, O))
    if hands is not None and hands_found is not None and np.any(hands_found):
        hands = np.asarray(hands, float)[np.asarray(hands_found, bool)]
        hpix, hz = project(P, hands)
        hdepth = hz / axis
        for j in range(len(hands)):
            front = (hdepth[:, j:j + 1] > 0.05) & (hdepth[:, j:j + 1] < depth + IN_FRONT_M)
            r_h = focal[:, None] * HAND_RADIUS_M / np.where(hdepth[:, j:j + 1] > 0.05, hdepth[:, j:j + 1], 1.0)
            d = np.linalg.norm(pix - hpix[:, j:j + 1], axis=-1)
            share = np.clip((d + radius - r_h) / np.maximum(2 * radius, 1e-9), 0.0, 1.0)
            visible *= np.where(front, share, 1.0)
    return np.where(inside, radius * np.maximum(visible, MIN_VISIBLE), 0.0)


def choose_views(scores: np.ndarray, k: int = VIEWS) -> np.ndarray:
    """(C,O) bool: each object's ``k`` best-scoring views (``k`` <= 0: every view that shows it);
    none for an object shown by fewer than two (it cannot be triangulated from the crops)."""
    C, O = scores.shape
    chosen = np.zeros((C, O), bool)
    for o in range(O):
        order = np.argsort(-scores[:, o], kind="stable")
        top = order[:k] if k > 0 else order
        top = top[scores[top, o] > 0]
        if len(top) >= 2:
            chosen[top, o] = True
    return chosen


@dataclass
class Held:
    """An object's detections from its last refresh: full-image pixels per camera, the first-stage
    centre then, its keypoints triangulated from them (for the next choice of views) and the frame
    sets since."""
    centre: np.ndarray
    detections: dict[str, tuple[np.ndarray, np.ndarray]]  # camera -> uv (k,2), confidence (k,)
    keypoints: np.ndarray | None
    age: int = 0


class ObjectSchedule:
    """Which objects the object stage crops on a frame set, and the detections reused for the rest.

    An object moving (its first-stage centre farther than ``rest_m`` from where it was at its last
    refresh), new, or not refreshed yet is cropped every frame set; a resting one every
    ``max_age + 1`` frame sets, at most ``resting_per_set`` of them per frame set (the stalest
    first), its last detections reused meanwhile (the cameras do not move; full-image pixels stay
    valid). An object the first stage does not find is forgotten. ``reuse=False``: every object
    found is cropped on every frame set."""

    def __init__(self, objects: int, rest_m: float = REST_M, max_age: int = MAX_AGE,
                 resting_per_set: int = RESTING_PER_SET, reuse: bool = True) -> None:
        self.held: list[Held | None] = [None] * objects
        self.kept_in_place = 0  # untouched objects the first stage missed or moved, kept where they were
        self.rest_m, self.max_age, self.resting_per_set = rest_m, max_age, resting_per_set
        self.reuse_resting = reuse  # False: every object found is cropped on every frame set
        self.refreshed = 0  # objects cropped, over all frame sets
        self.reused = 0  # objects whose last detections stood in for a crop

    def reset(self) -> None:
        self.held = [None] * len(self.held)

    def track(self, centres: np.ndarray, found: np.ndarray, hands: np.ndarray, near_m: float = BUSY_M
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(centres, found, kept): every placed object (held with keypoints) that no hand (``hands``
        (H,3) centres) is within ``near_m`` of is kept at its last centre where the first stage
        missed it or put it over ``JUMP_M`` away (nothing moved it); a ``kept`` object must be
        cropped there, so a crop that finds nothing (it was moved all the same) lets it go."""
        centres, found = np.array(centres, float), np.array(found, bool)
        kept = np.zeros(len(self.held), bool)
        hands = np.asarray(hands, float).reshape(-1, 3)
        for o, held in enumerate(self.held):
            if held is None or held.keypoints is None:
                continue
            if len(hands) and np.linalg.norm(hands - held.centre, axis=1).min() < near_m:
                continue
            if not found[o] or np.linalg.norm(centres[o] - held.centre) > JUMP_M:
                centres[o], found[o], kept[o] = held.centre, True, True
                self.kept_in_place += 1
        return centres, found, kept

    def plan(self, centres: np.ndarray, found: np.ndarray,
             busy: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(refresh (O,), reuse (O,)) for this frame set's first-stage centres (O,3) and ``found`` (O,);
        a ``busy`` object (O,) (a hand at it: it may move) is cropped every frame set."""
        O = len(self.held)
        refresh, reuse = np.zeros(O, bool), np.zeros(O, bool)
        resting = []
        for o in range(O):
            held = self.held[o]
            if not found[o]:
                self.held[o] = None
            elif (not self.reuse_resting or held is None or (busy is not None and busy[o])
                  or np.linalg.norm(centres[o] - held.centre) > self.rest_m):
                refresh[o] = True
            elif held.age >= self.max_age:
                resting.append(o)
            else:
                reuse[o] = True
        resting.sort(key=lambda o: -self.held[o].age)  # stable: equal ages by object order
        for i, o in enumerate(resting):
            refresh[o], reuse[o] = i < self.resting_per_set, i >= self.resting_per_set
        return refresh, reuse

    def keypoints(self, o: int, centre: np.ndarray) -> np.ndarray | None:
        """Object ``o``'s keypoints at its last refresh, moved with its centre since."""
        held = self.held[o]
        if held is None or held.keypoints is None:
            return None
        return held.keypoints + (np.asarray(centre) - held.centre)

    def store(self, o: int, centre: np.ndarray, detections: dict[str, tuple[np.ndarray, np.ndarray]],
              keypoints: np.ndarray | None) -> None:
        """Object ``o`` cropped now: its detections per camera and its keypoints triangulated from
        them (dropped when they collapse onto one place: they would say nothing about its extent)."""
        if keypoints is not None and (len(keypoints) < 2 or np.linalg.norm(
                keypoints - keypoints.mean(axis=0), axis=1).max() < MIN_EXTENT_M):
            keypoints = None
        self.held[o] = Held(np.array(centre, float), detections, keypoints)
        self.refreshed += 1

    def forget(self, o: int) -> None:
        self.held[o] = None

    def reuse(self, o: int) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        held = self.held[o]
        held.age += 1
        self.reused += 1
        return held.detections
