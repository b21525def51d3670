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

from dataclasses import dataclass, field

import numpy as np

from shared.demo import FINGERTIPS, KEYPOINTS_PER_HAND, TACTILE_REGIONS, Demo

THUMB_TIP, INDEX_TIP = FINGERTIPS["thumb"], FINGERTIPS["index"]
THUMB, INDEX = TACTILE_REGIONS.index("thumb"), TACTILE_REGIONS.index("index")
MOVED_M = 0.002  # an object has started to move once a point is this far from its start
GRASP_PULL = (0.03, 0.15)  # contact anchors: pulled fully within 3 cm, not at all beyond 15 cm
MATE_PULL = (0.10, 0.20)
APPROACH_CLEARANCE_M = 0.015  # the open gripper stays this high over the grasp point ...
APPROACH_OVER_M = (0.004, 0.010)  # ... until its pads are within 10 mm of it sideways (down fully within 4 mm)
DOCK_CLEARANCE_M = 0.004
MATE_DOCK = (0.005, 0.04)  # ... and docked onto the observed target within 4 cm of it (fully within 5 mm)
# aligned: the mate point within 2 mm of its target sideways, 5 mm in height (the snap-fit latches
# wherever it is pressed home under the world's 3 mm; at 3 mm a latched pair sagged to 3.1 mm when lifted)
MATED_M, MATED_DZ_M = 0.002, 0.005
LIFT_S = 0.5  # ... then lifted as high as the demonstrations did within this long (the teacher takes 0.4 s)


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


def _grasp(demo: Demo, moved_m: float = MOVED_M) -> tuple[int, int, int, np.ndarray]:
    """(hand, point, sample when the held object starts moving, pinch - point there)."""
    moved = np.linalg.norm(demo.objects - demo.objects[:1], axis=-1) > moved_m  # (T,K)
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


def shared_grasps(demos: list[Demo], moved_m: float = MOVED_M) -> tuple[list, str]:
    """Each demonstration's grasp (``_grasp``) and the object point they all grasp (raises
    AnchorError when there are none or they grasp different points)."""
    if not demos:
        raise AnchorError("no demonstrations to mine contact anchors from")
    names = demos[0].object_names
    grasps = [_grasp(d, moved_m) for d in demos]
    points = {names[k] for _, k, _, _ in grasps}
    if len(points) != 1:
        raise AnchorError(f"the demonstrations grasp different points: {sorted(points)}")
    return grasps, points.pop()


def mine_anchors(demos: list[Demo], moved_m: float = MOVED_M) -> ContactAnchors:
    """The grasp and mate anchors shared by ``demos`` (raises AnchorError where they disagree).
    ``moved_m``: how far a point must leave its start to count as moved (above the observation's
    noise: reconstructed demonstrations need more than the truth's ``MOVED_M``)."""
    grasps, grasp_point = shared_grasps(demos, moved_m)
    names = demos[0].object_names
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


@dataclass
class AnchorState:
    """Where the contact anchors stand in one run: reaching, holding the module, mated."""

    grasp_k: int  # object point indices: grasp point, held mate point, its target, the target's object
    mate_k: int
    target_k: int
    target_object: list[int]
    observed_hand: bool = False  # the policy observes its grasping hand at the gripper (hand feedback)
    held: bool = False  # the gripper is shut with the grasp point between its pads
    grasp_shift: np.ndarray = field(default_factory=lambda: np.zeros(3))  # the grasping hand's shift at the hold
    closing: bool = False  # the gripper is closing on the grasp point
    grasp_at: np.ndarray | None = None  # the grasp point the pinch is pulled onto
    across: np.ndarray = field(default_factory=lambda: np.zeros(3))  # the placement shift in force (first sample)
    docking: bool = False  # the mate point reached its target: docked until mated
    pressed_s: float = 0.0  # how long the mate has been pressed while aligned
    mated: bool = False  # pressed home: the policy's own height passes again (its lift)
    mated_at: np.ndarray | None = None  # the pads when mated (set at the first plan after)
    mated_pinch_z: float = 0.0  # the policy's lowest pinch height since
    mated_s: float = 0.0  # how long since pressed home (kept by the caller)

    def let_go(self) -> None:
        """The grip lost the grasp point: back to reaching."""
        self.held = self.mated = False
        self.mated_at, self.mated_s = None, 0.0


def _turn_about(points: np.ndarray, centre: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """(S, N, 3) points turned about gravity through (S, 3) centres by (S,) angles."""
    c, s = np.cos(angle)[:, None], np.sin(angle)[:, None]
    d = points - centre[:, None]
    out = points.copy()
    out[..., 0] = centre[:, None, 0] + c * d[..., 0] - s * d[..., 1]
    out[..., 1] = centre[:, None, 1] + s * d[..., 0] + c * d[..., 1]
    return out


def anchored_horizon(horizon: np.ndarray, g: int, anchors: ContactAnchors, objects: np.ndarray,
                     state: AnchorState, pads: np.ndarray, gripper_heading: float, flipped: bool,
                     plan_samples: int = 5, sample_dt: float = 0.02) -> np.ndarray:
    """The policy's horizon (S, P, 3) with its grasping hand ``g`` moved rigidly.

    Reaching: sample by sample, its pinch pulled onto the observed grasp point and its pinch line
    turned square to the object as demonstrated (all the way while the gripper closes). Holding: by the
    shift the grasp left; turned about its pinch so the held object takes the demonstrated heading
    to the target; shifted as a whole so the policy's intended placement (where the held mate
    point, carried along, comes closest to its observed target) lies over that target; and where
    it would be over the target, docked: the pads servo the observed mate point onto it and lower
    it to the target's height. Mated (pressed home while aligned): the sideways docking stays, the
    policy's own height passes (its lift), but not below the lift anchor: the demonstrations' lift
    (``anchors.lift_m``) reached LIFT_S after the mate. ``gripper_heading``: the gripper's thumb ->
    index heading now (robot kinematics); ``flipped``: the policy's index drives the gripper's thumb
    pad; ``plan_samples``: horizon samples until the next plan (the placement shift eases in over
    the horizon, and what has been eased in by then stays in force); ``sample_dt``: their spacing."""
    hand = slice(g * KEYPOINTS_PER_HAND, (g + 1) * KEYPOINTS_PER_HAND)
    pts = horizon[:, hand]
    pinches = pinch(pts)
    if not state.held:
        out = horizon.copy()
        if not state.closing or state.grasp_at is None:  # while closing: where it was (the fingers nudge it)
            state.grasp_at = objects[state.grasp_k] + anchors.grasp_offset
        grasp = state.grasp_at
        # once the horizon comes within reach of the grasp point its later samples stay there: before
        # a grasp the demonstrations never pass the grasp point by (the gripper lags the plan, and a
        # policy that turns away after its first sample arrived left the gripper short of it)
        pull = np.ones(len(pinches)) if state.closing else np.maximum.accumulate(
            pull_weights(np.linalg.norm(grasp - pinches, axis=-1), *GRASP_PULL))
        shift = pull[:, None] * (grasp - pinches)
        if not state.closing:  # approached from above: the open gripper descends only once over the
            # grasp point (coming in low from the side, a pad shoved the module away ahead of it)
            miss = float(np.linalg.norm((pads - grasp)[:2]))
            over = np.clip((miss - APPROACH_OVER_M[0]) / (APPROACH_OVER_M[1] - APPROACH_OVER_M[0]), 0.0, 1.0)
            low = grasp[2] + APPROACH_CLEARANCE_M * over - (pinches[:, 2] + shift[:, 2])
            shift[:, 2] += pull * np.maximum(low, 0.0)
        state.grasp_shift = shift[0]
        # the pinch line turned square to the object as demonstrated (either way round: a parallel pinch)
        square = heading(objects[state.mate_k] - objects[state.grasp_k]) + anchors.grasp_yaw
        line = np.arctan2(pts[:, INDEX_TIP, 1] - pts[:, THUMB_TIP, 1], pts[:, INDEX_TIP, 0] - pts[:, THUMB_TIP, 0])
        turn = pull * np.angle(np.exp(2j * (square - line))) / 2
        out[:, hand] = _turn_about(pts, pinches, turn) + shift[:, None]
        return out
    grasp_k, mate_k, target_k = state.grasp_k, state.mate_k, state.target_k
    if state.observed_hand:  # the policy's hand already starts where the gripper is
        state.grasp_shift = np.zeros(3)
    # heading: the held object keeps its offset to the gripper's; the gripper's at each sample is
    # the policy's thumb -> index heading, turned so the object's comes out as demonstrated
    held_heading = heading(objects[grasp_k] - objects[mate_k])
    wanted = heading(objects[state.target_object].mean(axis=0) - objects[target_k]) + anchors.mate_yaw
    a, b = (INDEX_TIP, THUMB_TIP) if flipped else (THUMB_TIP, INDEX_TIP)
    policy_heading = np.arctan2(pts[:, b, 1] - pts[:, a, 1], pts[:, b, 0] - pts[:, a, 0])
    turn = np.angle(np.exp(1j * (wanted - (held_heading - gripper_heading) - policy_heading)))
    goals = pinches + state.grasp_shift
    arm = _turn_about((objects[mate_k] - pads)[None, None], np.zeros((1, 3)), np.array([wanted - held_heading]))[0, 0]
    mate = goals + arm  # the held mate point at each sample, turned as wanted, if the pads follow the goals
    target = objects[target_k] + anchors.mate_offset
    nearest = mate[np.argmin(np.linalg.norm(mate[:, :2] - target[:2], axis=-1))]
    across = _flat(pull_onto(nearest[None], target, *MATE_PULL)[0])
    # eased in over the horizon from the one in force: a jump would fling the module out of the grip
    ease = np.minimum(1.0, np.arange(1, len(horizon) + 1) / len(horizon))[:, None]
    shift = state.grasp_shift + state.across + ease * (across - state.across)
    state.across = shift[min(plan_samples, len(shift)) - 1] - state.grasp_shift
    # docked where the mate point would be over its target: the pads servo the observed mate point
    # onto it (the policy's sideways motion there is noise at this scale) and lower it
    docked = pull_weights(np.linalg.norm((mate + across)[:, :2] - target[:2], axis=-1),
                          *MATE_DOCK)[:, None]
    # once the observed mate point is over its target it stays docked until pressed home: the
    # policy's next move (lifting, retreating) would otherwise pull it off before the press
    state.docking = state.docking or (not state.mated and float(np.linalg.norm(
        (objects[mate_k] - target)[:2])) < MATE_DOCK[1])
    if state.docking:
        docked = np.ones_like(docked)
    if not state.mated:
        servo = _flat(pads + target - objects[mate_k])[None] - _flat(pinches)
        # hovering just above until it is over the target (slid along the board it sticks short)
        above = DOCK_CLEARANCE_M if np.linalg.norm((objects[mate_k] - target)[:2]) > MATED_M else 0.0
        servo[:, 2] = target[2] + above - objects[mate_k][2] + pads[2] - pinches[:, 2]
    else:  # pressed home: the pads stay where they pressed (servoing on would drag the mated pair apart)
        # and the policy's lift passes: as it is where the policy observes its hand at the pads, else
        # counted from the pads and from the policy's lowest pinch since (the hold's shift is stale by
        # now: the policy moved on while the gripper dwelled and docked)
        if state.mated_at is None:
            state.mated_at, state.mated_pinch_z = pads.copy(), float(pinches[0, 2])
        state.mated_pinch_z = min(state.mated_pinch_z, float(pinches[0, 2]))
        servo = state.mated_at[None] - pinches
        servo[:, 2] = 0.0 if state.observed_hand else state.mated_at[2] - state.mated_pinch_z
        # the lift anchor: at least as high as the demonstrations lift what they assembled, at their
        # pace (the policy's own lift passes where higher)
        lift = anchors.lift_m * np.clip((state.mated_s + sample_dt * np.arange(1, len(horizon) + 1)) / LIFT_S, 0, 1)
        servo[:, 2] = np.maximum(servo[:, 2], state.mated_at[2] + lift - pinches[:, 2])
    shift = (1 - docked) * shift + docked * servo
    out = horizon.copy()
    out[:, hand] = _turn_about(pts, pinches, turn) + shift[:, None]
    return out


def _flat(v: np.ndarray) -> np.ndarray:
    """The horizontal part of (..., 3) vectors."""
    return np.asarray(v, float) * [1.0, 1.0, 0.0]
