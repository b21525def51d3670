"""Contact anchors: the contacts every demonstration makes, mined from the training demonstrations,
used at execution to close the last centimetres between the policy's goals and the observed objects.

The learned policy decides what to do, when, and roughly where; from three demonstrations its
hands settle about 1-2 cm from where the contact happens (docs/policy.md), while a 4 mm lens
needs about 2 mm. The demonstrations themselves say where the contacts are:

- the grasp anchor: the point of the first object that moves which the grasping hand's pinch
  (thumb-index midpoint) holds, the pinch's offset from it when the object starts to move, and
  the pinch line's heading against the object's (a parallel gripper closes square on it);
- the mate anchor: the pair of points, one on the held object and one on another object, that
  comes closest in every demonstration (the module's connector on the board's), with its offset;
- the lift anchor: how far every demonstration lifts the held object once mated (the module,
  carrying the board off the table);
- how hard: the grasping and pressing pressures the gloved demonstrations measured.

At execution (``execute_layout(anchored=True)``), a goal the policy puts near an anchor is pulled
onto the anchor as observed: fully within ``inner`` of it, fading to nothing at ``outer``. Pure
numpy; no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from shared.demo import FINGERTIPS, TACTILE_REGIONS, Demo

THUMB_TIP, INDEX_TIP = FINGERTIPS["thumb"], FINGERTIPS["index"]
THUMB, INDEX = TACTILE_REGIONS.index("thumb"), TACTILE_REGIONS.index("index")
MOVED_M = 0.002  # an object has started to move once a point is this far from its start


class AnchorError(ValueError):
    """The demonstrations do not show a consistent grasp or mate."""


@dataclass(frozen=True)
class ContactAnchors:
    grasp_point: str  # object point the pinch holds, e.g. "camera/lens"
    grasp_offset: np.ndarray  # (3,) pinch - grasp point, median over demonstrations
    grasp_yaw: float  # the pinch line's (thumb -> index) heading less the held object's (grasp -> mate point), mod pi
    mate_point: str  # point of the held object, e.g. "camera/connector"
    mate_target: str  # point of another object it is brought to, e.g. "board/connector"
    mate_offset: np.ndarray  # (3,) mate point - target at closest approach, median over demonstrations
    mate_spread_m: float  # how much the demonstrations disagree on that offset (largest deviation)
    mate_yaw: float  # held object's heading (mate -> grasp point) less the target's (target -> its object's centre)
    grasp_kpa: float  # the grasping thumb + index pressure the gloved demonstrations held (median peak)
    press_kpa: float  # the other hand's index pressure when it pressed (median peak over gloved demonstrations)
    lift_m: float = 0.0  # how far the grasp point rises after the mate (least over demonstrations)

    def to_dict(self) -> dict:
        return {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in self.__dict__.items()}


def pinch(hands: np.ndarray) -> np.ndarray:
    """(..., 21, 3) hand keypoints -> (..., 3) thumb-index midpoint."""
    return 0.5 * (hands[..., THUMB_TIP, :] + hands[..., INDEX_TIP, :])


def _object_of(name: str) -> str:
    return name.split("/", 1)[0]


def _grasp(demo: Demo) -> tuple[int, int, int, np.ndarray]:
    """(hand, point, sample when the held object starts moving, pinch - point there)."""
    moved = np.linalg.norm(demo.objects - demo.objects[:1], axis=-1) > MOVED_M  # (T,K)
    if not moved.any():
        raise AnchorError(f"demonstration {demo.meta.get('demo', '?')}: no object moves")
    t = int(np.argmax(moved.any(axis=1)))
    first = _object_of(demo.object_names[int(np.argmax(moved[t]))])
    points = [k for k, n in enumerate(demo.object_names) if _object_of(n) == first]
    pinches = pinch(demo.hands[t])  # (2,3)
    d = np.linalg.norm(pinches[:, None] - demo.objects[t, points][None], axis=-1)  # (2, points)
    h, j = np.unravel_index(int(np.argmin(d)), d.shape)
    k = points[j]
    return int(h), int(k), t, pinches[h] - demo.objects[t, k]


def mine_anchors(demos: list[Demo]) -> ContactAnchors:
    """The grasp and mate anchors shared by ``demos`` (raises AnchorError where they disagree)."""
    if not demos:
        raise AnchorError("no demonstrations to mine contact anchors from")
    names = demos[0].object_names
    grasps = [_grasp(d) for d in demos]
    grasp_points = {names[k] for _, k, _, _ in grasps}
    if len(grasp_points) != 1:
        raise AnchorError(f"the demonstrations grasp different points: {sorted(grasp_points)}")
    grasp_point = grasp_points.pop()
    held = _object_of(grasp_point)
    own = [k for k, n in enumerate(names) if _object_of(n) == held]
    other = [k for k, n in enumerate(names) if _object_of(n) != held]
    if not other:
        raise AnchorError("only one object: nothing to mate with")
    # per demonstration, each (held point, other point) pair's closest approach after the grasp
    closest = []
    for d, (_, _, t0, _) in zip(demos, grasps, strict=True):
        gap = d.objects[t0:, own][:, :, None] - d.objects[t0:, other][:, None]  # (T, own, other, 3)
        dist = np.linalg.norm(gap, axis=-1)
        at = dist.argmin(axis=0)
        closest.append((dist.min(axis=0), np.take_along_axis(gap, at[None, :, :, None], 0)[0], at + t0))
    worst = np.max([c for c, _, _ in closest], axis=0)  # a mate is close in every demonstration
    i, j = np.unravel_index(int(np.argmin(worst)), worst.shape)
    offsets = np.array([g[i, j] for _, g, _ in closest])
    mate_offset = np.median(offsets, axis=0)
    mate_k, target_k = own[i], other[j]
    grasp_k = names.index(grasp_point)
    if grasp_k == mate_k:
        raise AnchorError(f"the grasp and the mate are the same point ({grasp_point}): no heading to align")
    target_object = [k for k, n in enumerate(names) if _object_of(n) == _object_of(names[target_k])]
    turns = [relative_heading(d.objects[t[i, j]], grasp_k, mate_k, target_k, target_object)
             for d, (_, _, t) in zip(demos, closest, strict=True)]
    mate_yaw = float(np.angle(np.mean(np.exp(1j * np.array(turns)))))
    # a parallel pinch is the same turned by pi: average the doubled angles
    pinch_turns = [heading(d.hands[t0, h, INDEX_TIP] - d.hands[t0, h, THUMB_TIP])
                   - heading(d.objects[t0, mate_k] - d.objects[t0, grasp_k]) for d, (h, _, t0, _) in zip(demos, grasps,
                                                                                                       strict=True)]
    grasp_yaw = float(np.angle(np.mean(np.exp(2j * np.array(pinch_turns))))) / 2
    # the grasp point's highest rise after the mate, in the demonstration that lifts least
    lift = min(float((d.objects[t[i, j]:, grasp_k, 2] - d.objects[t[i, j], grasp_k, 2]).max())
               for d, (_, _, t) in zip(demos, closest, strict=True))
    return ContactAnchors(grasp_point, np.median([o for *_, o in grasps], axis=0), grasp_yaw, names[own[i]],
                          names[other[j]],
                          mate_offset, float(np.linalg.norm(offsets - mate_offset, axis=-1).max()), mate_yaw,
                          _peak(demos, [h for h, *_ in grasps], (THUMB, INDEX), "grasping"),
                          _peak(demos, [1 - h for h, *_ in grasps], (INDEX,), "pressing"), max(lift, 0.0))


def _peak(demos: list[Demo], hands: list[int], regions: tuple[int, ...], role: str) -> float:
    """Median over the demonstrations with a glove on that hand of the peak summed pressure."""
    peaks = [float(d.tactile[:, h, list(regions)].sum(axis=-1).max()) for d, h in zip(demos, hands, strict=True)
             if d.tactile_mask[:, h, list(regions)].all()]
    if not peaks:
        raise AnchorError(f"no demonstration has a glove on the {role} hand")
    return float(np.median(peaks))


def heading(v: np.ndarray) -> float:
    """Angle of a vector about gravity (rad)."""
    return float(np.arctan2(v[1], v[0]))


def relative_heading(objects: np.ndarray, grasp_k: int, mate_k: int, target_k: int, target_object: list[int]) -> float:
    """Heading of the held object (its mate point -> grasp point) less the target object's (its
    mate target -> the centre of its points), wrapped to (-pi, pi]."""
    d = (heading(objects[grasp_k] - objects[mate_k])
         - heading(objects[target_object].mean(axis=0) - objects[target_k]))
    return float(np.angle(np.exp(1j * d)))


def pull_weights(distance: np.ndarray, inner: float, outer: float) -> np.ndarray:
    """1 within ``inner``, 0 beyond ``outer``, linear between."""
    return np.clip((outer - np.asarray(distance, float)) / max(outer - inner, 1e-9), 0.0, 1.0)


def pull_onto(points: np.ndarray, target: np.ndarray, inner: float, outer: float) -> np.ndarray:
    """(T,3) goal points near ``target`` (3,) -> the shift (T,3) that pulls each onto it by
    pull_weights of its distance."""
    gap = np.asarray(target, float)[None] - points
    return pull_weights(np.linalg.norm(gap, axis=-1), inner, outer)[:, None] * gap
