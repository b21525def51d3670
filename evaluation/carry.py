"""Contact anchors of the carry tasks (pick_place, wiping): mined from the training demonstrations,
used by the robot loop of evaluation/execute_carry.py to close the last centimetres the policy
leaves. Pure numpy; no I/O.

- grasp anchor (as the assembly's, evaluation/anchors.py): the point the grasping pinch holds
  when its object starts to move, the pinch's offset from it, the thumb-index width there and the
  demonstrated grip pressure;
- place anchor (pick_place): where the held object's placed point ends against its target (the
  box's bottom on the plate's centre), median over the demonstrations;
- contact anchor (wiping): the held object's contact point (the pad's face) is lowered onto the
  target's surface wherever the policy brings it over the target and close above it, and pressed
  with the demonstrated force (force control).

The policy still chooses the hand, the path (on wiping: the path over the area) and when to grasp
and let go (its predicted touch).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from evaluation.anchors import (
    APPROACH_CLEARANCE_M,
    APPROACH_OVER_M,
    GRASP_PULL,
    INDEX,
    MATE_PULL,
    MOVED_M,
    THUMB,
    AnchorError,
    pinch,
    pull_weights,
    shared_grasps,
)
from services.world.teacher import KPA_PER_N
from shared.demo import FINGERTIPS, KEYPOINTS_PER_HAND, TACTILE_REGIONS, Demo

THUMB_TIP, INDEX_TIP = FINGERTIPS["thumb"], FINGERTIPS["index"]
PRESS_REGIONS = tuple(TACTILE_REGIONS.index(r) for r in ("middle", "ring", "palm"))  # wiping's press (wiping.py)
# which points place / touch what, per carry task (the registry's success tests name them)
PLACE = {"pick_place": ("box/bottom", "plate/center")}
CONTACT = {"wiping": ("sponge/bottom", "plate/center")}
CONTACT_ABOVE_M = 0.03  # contact anchor: the pad within 3 cm above the plate (over it) is lowered onto it
CONTACT_MARGIN_M = 0.01  # ... over the plate: within its marked area grown by 1 cm


@dataclass(frozen=True)
class CarryAnchors:
    grasp_point: str  # the object point the pinch holds, e.g. "box/top"
    grasp_offset: np.ndarray  # (3,) pinch - grasp point when the object starts to move (median)
    grasp_width_m: float  # thumb-index distance there (median): the open gripper opens at least this wide
    grasp_kpa: float  # the grasping thumb + index pressure (median peak over gloved demonstrations)
    place_point: str | None = None  # pick_place: the held point set on the target, and the target
    place_target: str | None = None
    place_offset: np.ndarray | None = None  # (3,) place point - target at the demonstration's end (median)
    contact_point: str | None = None  # wiping: the held point pressed onto the target's surface, and the target
    contact_target: str | None = None
    press_n: float = 0.0  # wiping: the demonstrated press (median over gloved demonstrations of its median)

    def to_dict(self) -> dict:
        return {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in self.__dict__.items()}


def mine_carry_anchors(task: str, demos: list[Demo], moved_m: float = MOVED_M) -> CarryAnchors:
    """The anchors ``demos`` of ``task`` share (raises AnchorError where they disagree)."""
    grasps, grasp_point = shared_grasps(demos, moved_m)
    names = demos[0].object_names
    width = float(np.median([np.linalg.norm(d.hands[t0, h, INDEX_TIP] - d.hands[t0, h, THUMB_TIP])
                             for d, (h, _, t0, _) in zip(demos, grasps, strict=True)]))
    gloved = [(d, h) for d, (h, *_) in zip(demos, grasps, strict=True) if d.tactile_mask[:, h, [THUMB, INDEX]].all()]
    if not gloved:
        raise AnchorError("no demonstration has a glove on the grasping hand")
    grasp_kpa = float(np.median([d.tactile[:, h, [THUMB, INDEX]].sum(axis=-1).max() for d, h in gloved]))
    out = dict(grasp_point=grasp_point, grasp_offset=np.median([o for *_, o in grasps], axis=0),
               grasp_width_m=width, grasp_kpa=grasp_kpa)
    if task in PLACE:
        point, target = PLACE[task]
        k, j = names.index(point), names.index(target)
        out.update(place_point=point, place_target=target,
                   place_offset=np.median([d.objects[-1, k] - d.objects[-1, j] for d in demos], axis=0))
    if task in CONTACT:
        press = [np.median(p[p > 0.5]) for p in (d.tactile[:, h][:, list(PRESS_REGIONS)].sum(axis=-1) / KPA_PER_N
                                                  for d, h in gloved) if (p > 0.5).any()]
        if not press:
            raise AnchorError("no gloved demonstration presses")
        out.update(contact_point=CONTACT[task][0], contact_target=CONTACT[task][1], press_n=float(np.median(press)))
    return CarryAnchors(**out)


@dataclass
class CarryState:
    """Where the anchors stand in one run."""

    held: bool = False  # the gripper is shut with the grasp point between its pads
    closing: bool = False  # the gripper is closing on the grasp point
    grasp_at: np.ndarray | None = None  # the grasp point the pinch is pulled onto while closing
    released: bool = False  # the policy's touch let go of what it held: the anchors are done


def over_area(point: np.ndarray, corners: np.ndarray, margin: float) -> bool:
    """Whether ``point`` (3,) lies over the rectangle of ``corners`` (4,3: a0, a1, a2, a3), grown by
    ``margin``."""
    a0, a1, _, a3 = corners
    ex, ey = a1 - a0, a3 - a0
    rel = point - 0.5 * (a0 + corners[2])
    u = abs(float(rel[:2] @ ex[:2])) / max(float(np.linalg.norm(ex[:2])), 1e-9)
    v = abs(float(rel[:2] @ ey[:2])) / max(float(np.linalg.norm(ey[:2])), 1e-9)
    return u <= 0.5 * np.linalg.norm(ex[:2]) + margin and v <= 0.5 * np.linalg.norm(ey[:2]) + margin


def carry_horizon(horizon: np.ndarray, g: int, anchors: CarryAnchors, objects: np.ndarray, names: list[str],
                  state: CarryState, pads: np.ndarray, area: np.ndarray | None = None,
                  depth: float = 0.0) -> np.ndarray:
    """The policy's horizon (S, P, 3) with its grasping hand ``g`` moved rigidly by the anchors.

    Reaching: its pinch pulled onto the observed grasp point (fully within 3 cm, not beyond 15 cm;
    once within reach, later samples stay there), the open gripper descending only once over it.
    Holding: the held object moves with the pads, so a sample's goal carries the held point to
    ``objects[point] + goal - pads``; pick_place: pulled onto the place target (fully within 10 cm,
    not beyond 20 cm); wiping: where the pad would be over the marked area (``area``, 4 corners)
    and within CONTACT_ABOVE_M above its surface, lowered onto it. Released: as the policy put it.
    ``depth``: the robot mapping's grasp depth (the horizon's pinch is already that far below the
    hand's; the grasp anchor too)."""
    if state.released:  # placed: the policy's own retreat (a grasp pull would bring the gripper back)
        return horizon
    hand = slice(g * KEYPOINTS_PER_HAND, (g + 1) * KEYPOINTS_PER_HAND)
    pts = horizon[:, hand]
    pinches = pinch(pts)
    shift = np.zeros_like(pinches)
    if not state.held:
        if not state.closing or state.grasp_at is None:
            state.grasp_at = objects[names.index(anchors.grasp_point)] + anchors.grasp_offset - [0.0, 0.0, depth]
        grasp = state.grasp_at
        pull = np.ones(len(pinches)) if state.closing else np.maximum.accumulate(
            pull_weights(np.linalg.norm(grasp - pinches, axis=-1), *GRASP_PULL))
        shift = pull[:, None] * (grasp - pinches)
        if not state.closing:  # from above: down only once the pads are over the grasp point
            miss = float(np.linalg.norm((pads - grasp)[:2]))
            over = np.clip((miss - APPROACH_OVER_M[0]) / (APPROACH_OVER_M[1] - APPROACH_OVER_M[0]), 0.0, 1.0)
            low = grasp[2] + APPROACH_CLEARANCE_M * over - (pinches[:, 2] + shift[:, 2])
            shift[:, 2] += pull * np.maximum(low, 0.0)
    elif anchors.place_point is not None:
        carried = objects[names.index(anchors.place_point)] + pinches - pads
        target = objects[names.index(anchors.place_target)] + anchors.place_offset
        w = np.maximum.accumulate(pull_weights(np.linalg.norm((target - carried)[:, :2], axis=-1), *MATE_PULL))
        shift = w[:, None] * (target - carried)
    elif anchors.contact_point is not None and area is not None:
        carried = objects[names.index(anchors.contact_point)] + pinches - pads
        surface = float(area[:, 2].mean())
        for i, c in enumerate(carried):
            if over_area(c, area, CONTACT_MARGIN_M) and c[2] - surface < CONTACT_ABOVE_M:
                shift[i, 2] = surface - c[2]
    out = horizon.copy()
    out[:, hand] = pts + shift[:, None]
    return out
