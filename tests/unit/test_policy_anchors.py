"""Contact anchors: mined from the training demonstrations, and what they do to the goals the
robot executes (evaluation/anchors.py: mined, and applied by anchored_horizon)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import evaluation.anchors as an
import evaluation.execute as ex
from evaluation.anchors import AnchorError, mine_anchors, pinch, pull_onto, pull_weights
from services.world.teacher import assembly_protocol


@pytest.fixture(scope="module")
def demos():
    return assembly_protocol(0)


def test_the_demonstrations_show_the_grasp_the_mate_and_how_hard(demos):
    a = mine_anchors(demos[:3])
    assert a.grasp_point == "camera/lens" and np.linalg.norm(a.grasp_offset) < 1e-3
    assert (a.mate_point, a.mate_target) == ("camera/connector", "board/connector")
    assert np.linalg.norm(a.mate_offset) < 2e-3 and a.mate_spread_m < 2e-3
    assert abs(a.mate_yaw) < 0.05  # the module lies across the board, lens end over it
    assert a.grasp_kpa == pytest.approx(60.0) and a.press_kpa == pytest.approx(60.0)
    # the same anchors from other demonstrations of the task; the pressure needs a glove on that hand
    b = mine_anchors([demos[2], demos[5], demos[6]])
    assert (b.grasp_point, b.mate_point, b.mate_target) == (a.grasp_point, a.mate_point, a.mate_target)
    with pytest.raises(AnchorError, match="glove on the pressing hand"):
        mine_anchors(demos[5:8])  # gloved on the grasping hand only


def test_demonstrations_without_a_grasp_are_refused(demos):
    still = demos[0]
    frozen = type(still)(**{**still.__dict__, "objects": np.repeat(still.objects[:1], still.steps, 0)})
    with pytest.raises(AnchorError, match="no object moves"):
        mine_anchors([frozen])
    with pytest.raises(AnchorError, match="no demonstrations"):
        mine_anchors([])


def test_a_pull_is_whole_inside_and_fades_to_nothing_outside():
    np.testing.assert_allclose(pull_weights([0.0, 0.03, 0.045, 0.06, 0.2], 0.03, 0.06), [1, 1, 0.5, 0, 0])
    target = np.array([0.1, 0.0, 0.0])
    pts = np.array([[0.1, 0.02, 0.0], [0.1, 0.045, 0.0], [0.1, 0.3, 0.0]])
    moved = pts + pull_onto(pts, target, 0.03, 0.06)
    np.testing.assert_allclose(moved[0], target, atol=1e-12)  # inside: onto the target
    np.testing.assert_allclose(moved[1], [0.1, 0.0225, 0.0], atol=1e-12)  # halfway out: halfway
    np.testing.assert_allclose(moved[2], pts[2])  # far away: untouched


def _horizon(pinches: np.ndarray, g: int = 0) -> np.ndarray:
    """(S, 42 + 5, 3): a grasping hand whose thumb and index straddle the given pinches along x."""
    h = np.zeros((len(pinches), 47, 3))
    base = g * 21
    h[:, base:base + 21] = pinches[:, None]
    h[:, base + 4] = pinches - [0.003, 0.0, 0.0]
    h[:, base + 8] = pinches + [0.003, 0.0, 0.0]
    return h


def test_reaching_pulls_the_pinch_onto_the_observed_grasp_point(demos):
    a = mine_anchors(demos[:3])
    names = demos[0].object_names
    objects = demos[3].objects[0].astype(float)
    lens = objects[names.index("camera/lens")]
    state = an.AnchorState(names.index("camera/lens"), names.index("camera/connector"),
                           names.index("board/connector"), [names.index(f"board/{p}") for p in
                                                            ("c0", "c1", "c2", "c3", "connector")])
    pinches = lens + np.array([[0.3, 0.0, 0.2], [0.0, 0.015, 0.01], [0.0, 0.0, 0.012]])
    over = lens + [0.0, 0.0, 0.02]  # the gripper's pads right over the lens
    out = an.anchored_horizon(_horizon(pinches), 0, a, objects, state, over, 0.0, False)
    got = pinch(out[:, :21])
    np.testing.assert_allclose(got[0], pinches[0])  # the policy is still far away: its goal stands
    np.testing.assert_allclose(got[1:], [lens, lens], atol=1e-12)  # close by: on the lens exactly
    np.testing.assert_allclose(out[:, 21:], _horizon(pinches)[:, 21:])  # the other hand and objects untouched
    line = out[1, 8] - out[1, 4]
    assert np.linalg.norm(line) == pytest.approx(0.006) and line[2] == pytest.approx(0.0)  # same aperture
    # ... and turned square to the module as demonstrated (either way round)
    axis = objects[names.index("camera/connector")] - lens
    turned = np.arctan2(line[1], line[0]) - np.arctan2(axis[1], axis[0]) - a.grasp_yaw
    assert np.sin(turned) == pytest.approx(0.0, abs=1e-9)
    # a horizon that arrives and then turns away: it stays on the lens (the gripper lags the plan)
    away = lens + np.array([[0.3, 0.0, 0.2], [0.0, 0.0, 0.01], [0.2, 0.1, 0.1]])
    got = pinch(an.anchored_horizon(_horizon(away), 0, a, objects, state, over, 0.0, False)[:, :21])
    np.testing.assert_allclose(got[0], away[0])
    np.testing.assert_allclose(got[1:], [lens, lens], atol=1e-12)
    # the pads still 3 cm off to the side: the gripper comes in over the lens, not low from the side
    beside = lens + [0.03, 0.0, 0.005]
    got = pinch(an.anchored_horizon(_horizon(pinches), 0, a, objects, state, beside, 0.0, False)[:, :21])
    np.testing.assert_allclose(got[1:], [lens + [0, 0, an.APPROACH_CLEARANCE_M]] * 2, atol=1e-12)
    state.closing = True  # closing the gripper: every sample dwells on the lens
    out = an.anchored_horizon(_horizon(pinches), 0, a, objects, state, beside, 0.0, False)
    np.testing.assert_allclose(pinch(out[:, :21]), np.repeat(lens[None], 3, 0), atol=1e-12)


def test_holding_turns_and_docks_the_module_onto_its_target(demos):
    a = mine_anchors(demos[:3])
    names = demos[0].object_names
    idx = {n: i for i, n in enumerate(names)}
    board = [idx[f"board/{p}"] for p in ("c0", "c1", "c2", "c3", "connector")]
    objects = demos[3].objects[0].astype(float).copy()
    target = objects[idx["board/connector"]]
    # the module held 4 cm beside the target, its lens end pointing the wrong way (+y)
    pads = target + [0.0, 0.04, 0.03]
    objects[idx["camera/lens"]] = pads
    objects[idx["camera/connector"]] = pads - [0.0, 0.036, 0.0]
    state = an.AnchorState(idx["camera/lens"], idx["camera/connector"], idx["board/connector"], board, held=True)
    pinches = np.repeat(pads[None], 4, 0)  # the policy wants to stay where it is
    out = an.anchored_horizon(_horizon(pinches), 0, a, objects, state, pads, 0.0, False)
    # the gripper turns by the difference between the module's heading and the wanted one
    wanted = np.arctan2(*(objects[board].mean(axis=0) - target)[[1, 0]]) + a.mate_yaw
    held = np.arctan2(*(objects[idx["camera/lens"]] - objects[idx["camera/connector"]])[[1, 0]])
    d = out[0, 8] - out[0, 4]
    turned = np.arctan2(d[1], d[0])
    assert np.angle(np.exp(1j * (turned - (wanted - held)))) == pytest.approx(0.0, abs=1e-9)
    # docked: the goals move the pads by the observed mate point's miss, and down to the target's height
    target = target + a.mate_offset
    np.testing.assert_allclose(pinch(out[:, :21])[:, :2],
                               np.repeat((pads + target - objects[idx["camera/connector"]])[None, :2], 4, 0),
                               atol=1e-9)
    hover = an.DOCK_CLEARANCE_M  # still 4 cm off sideways: it comes in just above the target's height
    np.testing.assert_allclose(pinch(out[:, :21])[:, 2],
                               pads[2] + target[2] + hover - objects[idx["camera/connector"]][2])
    state.mated = True  # pressed home: the pads stay where they pressed, the policy's lift passes from there
    a = dataclasses.replace(a, lift_m=0.0)  # (without the lift anchor: test_the_lift_anchor_...)
    pressed = pads - [0.0, 0.0, 0.03]
    still_lowering = pinches - [0.0, 0.0, 0.01]  # the policy is still on its way down: no lift yet
    out = an.anchored_horizon(_horizon(still_lowering), 0, a, objects, state, pressed, 0.0, False)
    np.testing.assert_allclose(pinch(out[:, :21]), np.repeat(pressed[None], 4, 0), atol=1e-12)
    lift = pinches + np.linspace(0.0, 0.05, 4)[:, None] * [0.0, 0.0, 1.0]  # up 5 cm from its lowest
    out = an.anchored_horizon(_horizon(lift), 0, a, objects, state, pads, 0.0, False)
    np.testing.assert_allclose(pinch(out[:, :21]), pressed + (lift - still_lowering[0]) * [0, 0, 1], atol=1e-12)
    state.observed_hand = True  # the policy sees its hand at the pads (hand feedback): its own height passes
    out = an.anchored_horizon(_horizon(lift), 0, a, objects, state, pads, 0.0, False)
    np.testing.assert_allclose(pinch(out[:, :21])[:, 2], lift[:, 2], atol=1e-12)


def test_the_lift_anchor_raises_the_mated_module_as_high_as_every_demonstration_did(demos):
    a = mine_anchors(demos[:3])
    # the teacher lifts the module about 5 cm once it is pressed home (it carries the board along)
    assert 0.03 < a.lift_m < 0.07
    names = demos[0].object_names
    idx = {n: i for i, n in enumerate(names)}
    objects = demos[3].objects[0].astype(float)
    state = an.AnchorState(idx["camera/lens"], idx["camera/connector"], idx["board/connector"],
                           [idx[f"board/{p}"] for p in ("c0", "c1", "c2", "c3", "connector")], observed_hand=True,
                           held=True, docking=True, mated=True)
    pressed = objects[idx["board/connector"]] + [0.0, 0.03, 0.01]
    still = np.repeat(pressed[None], 4, 0)  # the policy, seeing its hand at the pads, does not lift
    out = an.anchored_horizon(_horizon(still), 0, a, objects, state, pressed, 0.0, False, sample_dt=0.1)
    # at the demonstrations' pace: all of it LIFT_S after the mate
    rise = a.lift_m * np.minimum(1, np.arange(1, 5) * 0.1 / an.LIFT_S)
    np.testing.assert_allclose(pinch(out[:, :21])[:, 2], pressed[2] + rise, atol=1e-12)
    np.testing.assert_allclose(pinch(out[:, :21])[:, :2], still[:, :2], atol=1e-12)  # straight up
    state.mated_s = 0.2  # later: further up, from the height where it was pressed home
    out = an.anchored_horizon(_horizon(still + [0, 0, 0.01]), 0, a, objects, state, pressed + [0, 0, 0.01], 0.0,
                              False, sample_dt=0.1)
    rise = a.lift_m * np.minimum(1, (0.2 + np.arange(1, 5) * 0.1) / an.LIFT_S)
    np.testing.assert_allclose(pinch(out[:, :21])[:, 2], pressed[2] + rise, atol=1e-12)
    higher = still + np.linspace(0.02, 0.1, 4)[:, None] * [0.0, 0.0, 1.0]  # the policy's own lift passes
    out = an.anchored_horizon(_horizon(higher), 0, a, objects, state, pressed, 0.0, False, sample_dt=0.1)
    assert pinch(out[:, :21])[-1, 2] == pytest.approx(higher[-1, 2], abs=1e-12)
    state.let_go()  # the grip lost the module: the lift is over
    assert state.mated_s == 0.0 and not state.mated and state.mated_at is None


@pytest.mark.slow
def test_anchors_recover_a_teacher_whose_hand_is_off_by_two_centimetres(monkeypatch, demos):
    """Physically, in the loop: the teacher's own grasping hand displaced by 2 cm misses the lens
    and nothing is assembled; with the anchors the same hand grasps, places, presses and lifts."""
    offset = np.array([0.02, 0.0, 0.0])

    class OffsetTeacher(ex.TeacherReplay):
        def _state(self, t):
            st = super()._state(t)
            st.hands[ex.HAND_NAMES.index(self.teacher.grasp_hand)] += offset
            return st

    monkeypatch.setattr(ex, "TeacherReplay", OffsetTeacher)
    plain = ex.execute_layout(None, seed=0, demo=4)
    assert not plain.success and plain.object_motion_mm < 20.0 and plain.closest_mm > 5.0
    anchored = ex.execute_layout(None, seed=0, demo=4, anchors=mine_anchors(demos[:3]))
    assert anchored.closest_mm < 3.0 and anchored.seated and anchored.success, anchored
