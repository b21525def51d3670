"""Robot in the loop (`xm eval --execute`): the loop with an untrained policy for a few tenths of a
second, the whole assembly with the teacher's own hands, and the pure helpers."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

import evaluation.execute as ex
import evaluation.robot_eval as re_
from evaluation.evaluate import main as eval_main
from evaluation.execute import (
    anchored_press,
    execute_layout,
    grasping_hand,
    gripper_flipped,
    hand_point_names,
    learned_squeeze,
    observed_hands,
)
from learning.ours import Ours
from learning.presets import preset
from services.policy.model import Policy
from services.world.teacher import assembly_protocol


def test_policy_drives_the_simulated_robot_through_trajopt_and_the_board(tmp_path):
    torch.set_num_threads(1)
    demos = assembly_protocol(0)
    model = Ours(preset("single_state", hidden=(32, 32), steps=3, batch=16, eval_every=10 ** 6))
    model.fit(demos[:2], progress=False)
    r = execute_layout(model.policy, seed=0, demo=3, seconds=0.4)
    assert r.grasp_hand == "right" and r.demo == 3  # the protocol's layout 3: a right-hand grasp
    # 4 plans in 0.4 s; an untrained net may ask for unreachable goals (rejected: the robot holds)
    assert abs(r.seconds - 0.4) < 0.05 and np.isfinite(r.tracking_mm) and r.solves_rejected <= 4
    assert not r.success and r.object_motion_mm < 5.0  # an untrained net does not assemble anything
    assert np.isfinite(r.closest_mm) and 0.0 <= r.opening_mm <= 80.0 + 1e-6
    model.save(str(tmp_path / "p.pt"))
    assert eval_main(["--execute", "--checkpoint", str(tmp_path / "missing.pt"), "--out", str(tmp_path)]) == 2


def _spied_tiny_policy(monkeypatch) -> tuple[list, list, Policy]:
    """A briefly trained net, and lists that fill with the hands each policy step observes and
    the hands it returns."""
    seen, returned = [], []
    step = ex.PolicyRunner.step

    def spy(self, scene):
        seen.append(scene.hands.copy())
        out = step(self, scene)
        returned.append(out[:42].reshape(2, 21, 3).copy())
        return out

    monkeypatch.setattr(ex.PolicyRunner, "step", spy)
    torch.set_num_threads(1)
    model = Ours(preset("single_state", hidden=(32, 32), steps=3, batch=16, eval_every=10 ** 6))
    model.fit(assembly_protocol(0)[:2], progress=False)
    return seen, returned, model.policy


def test_the_policy_is_fed_its_own_next_hands(monkeypatch):
    """The interactive neural simulation: each step observes the hands the previous step predicted
    (it once observed its start hands over and over, so the robot followed a standing policy)."""
    seen, returned, model = _spied_tiny_policy(monkeypatch)
    execute_layout(model, seed=0, demo=4, seconds=0.1)
    assert len(seen) >= 4
    for k in range(1, len(seen)):
        np.testing.assert_allclose(seen[k], returned[k - 1])
    assert np.abs(seen[-1] - seen[0]).max() > 1e-6  # the hands moved


def test_hand_feedback_moves_the_grasping_hand_onto_the_gripper(monkeypatch):
    """--hand-feedback: from the second step the grasping hand the policy observes is its own
    prediction moved rigidly (every point by one translation) onto the gripper's pads; the pressing
    hand stays the policy's own."""
    seen, returned, model = _spied_tiny_policy(monkeypatch)
    # layout 4: a left-hand grasp; observed from the first step (catch_m=None)
    r = execute_layout(model, seed=0, demo=4, seconds=0.1, feedback=True, catch_m=None)
    g, p = (0, 1) if r.chosen_hand == "left" else (1, 0)
    shifts = [seen[k][g] - returned[k - 1][g] for k in range(1, len(seen))]
    for s in shifts:
        np.testing.assert_allclose(s, np.repeat(s[:1], 21, axis=0), atol=1e-12)  # one rigid translation
    assert max(np.abs(s).max() for s in shifts) > 1e-4  # the robot is not where the policy's hand is
    for k in range(1, len(seen)):
        np.testing.assert_allclose(seen[k][p], returned[k - 1][p])
    assert np.isfinite(r.policy_closest_mm)


def test_hand_feedback_waits_until_the_gripper_has_caught_up_with_the_policys_hand():
    """The gripper starts where no demonstrated hand was: the policy observes its grasping hand
    there only once the pads have come within catch_m of its own pinch, and from then on."""
    hands = np.zeros((2, 21, 3))
    hands[1] += [0.1, 0.2, 0.3]  # the right hand's pinch (thumb-index midpoint) at (0.1, 0.2, 0.3)
    far, near = np.array([0.1, 0.25, 0.3]), np.array([0.1, 0.22, 0.3])  # 50 and 20 mm away
    out, observing = observed_hands(hands, 1, far, False, 0.03)
    assert not observing and out is hands
    out, observing = observed_hands(hands, 1, near, False, 0.03)
    assert observing
    np.testing.assert_allclose(out[1], hands[1] + [0.0, 0.02, 0.0], atol=1e-12)  # moved rigidly onto the pads
    np.testing.assert_allclose(out[0], hands[0])  # the other hand is the policy's own
    out, observing = observed_hands(hands, 1, far, True, 0.03)  # caught up once: observed from then on
    assert observing
    np.testing.assert_allclose(out[1], hands[1] + [0.0, 0.05, 0.0], atol=1e-12)
    out, observing = observed_hands(hands, 1, far, False, None)  # no catch distance: at once
    assert observing and np.allclose(out[1], hands[1] + [0.0, 0.05, 0.0])
    assert np.all(hands[1] == [0.1, 0.2, 0.3])  # the input is left as it was


def test_execute_writes_the_success_rate(tmp_path, monkeypatch):
    calls = []

    def fake(model, seed, demo, **kw):  # the loop itself is tested above; here only the report
        calls.append(demo)
        return ex.ExecutionResult(seed, demo, "left", "left", demo == 3, 9.0, 10.0, 0, 1.0, 20.0, 30.0, 0.0, 5.0,
                                  demo == 3)

    monkeypatch.setattr(re_, "execute_layout", fake)  # where `xm eval --execute` calls it
    demos = assembly_protocol(0)
    model = Ours(preset("single_state", hidden=(16,), steps=1, batch=8, eval_every=10 ** 6))
    model.fit(demos[:1], progress=False)
    model.save(str(tmp_path / "p.pt"))
    assert eval_main(["--execute", "--checkpoint", str(tmp_path / "p.pt"), "--layouts", "2", "--out",
                      str(tmp_path), "--no-progress", "--variants", "anchored"]) == 0
    report = json.loads((tmp_path / "execute.json").read_text())
    assert calls == [3, 4] and report["rows"][0]["success_rate"] == 0.5 and report["anchors"] is not None


@pytest.mark.slow
def test_the_cell_assembles_the_camera_with_the_teachers_own_hands(tmp_path):
    """Everything but the policy, physically: the gripper reaches the 4 mm lens body, grasps and
    carries the 3 g module, the wrist follows the pinch's yaw, the connector is placed within 3 mm,
    pressed home (the snap-fit latches) and the board comes up with the module. Layout 5 is a
    right-hand demonstration: the grasping hand drives the gripper whatever its side."""
    for demo, hand in ((4, "left"), (5, "right")):
        r = execute_layout(None, seed=0, demo=demo)
        assert r.grasp_hand == r.chosen_hand == hand
        assert r.closest_mm < 3.0 and r.object_motion_mm > 100.0
        assert r.connector_gap_mm < 3.0 and r.seated and r.success, r
    assert eval_main(["--execute", "--teacher", "--layouts", "1", "--out", str(tmp_path), "--no-progress"]) == 0
    report = json.loads((tmp_path / "execute.json").read_text())
    assert report["checkpoint"] == "teacher" and all(r["success_rate"] == 1.0 for r in report["rows"]
                                                     if r["variant"] == "anchored")


def test_the_learned_policys_weak_predicted_touch_on_the_lens_shuts_the_gripper_and_holds():
    """Without anchors, predicted touch alone closes the gripper: the nets predict 3.5-5 kPa of
    grasping touch while their pinch is on the lens, so the gripper shuts there, and it opens again
    only once the prediction falls below half the threshold."""
    on = False
    for kpa, want in ((1.0, False), (3.5, True), (2.0, True), (4.5, True), (1.4, False), (2.0, False)):
        on = learned_squeeze(on, kpa, ex.LEARNED_GRASP_KPA)
        assert on is want, (kpa, on)
    assert not learned_squeeze(False, 50.0, None)  # no touch channel: the fingers follow the pinch only


def test_roles_are_read_from_the_rollout_and_the_gripper_keeps_its_wrist_in_range():
    t = np.linspace(0, 1, 50)[:, None]
    hands = np.zeros((50, 2, 21, 3))
    hands[:, 0] = [0.2, 0.3, 0.1]  # the left hand stays away
    reach = (1 - t) * np.array([0.0, -0.3, 0.1]) + t * np.array([0.05, 0.05, 0.004])
    hands[:, 1] = reach[:, None]  # the right one reaches the module
    assert grasping_hand(hands, np.array([0.05, 0.05, 0.0])) == "right"
    names = hand_point_names("right", flipped=True)
    assert names[21 + 4] == "left/8" and names[21 + 8] == "left/4" and names[0] == "right/0" and names[4] == "right/4"
    assert hand_point_names("left")[4] == "left/4"
    # a pinch line turning from 80 to 280 deg: unflipped the wrist would need 170..370 deg
    ang = np.radians(np.linspace(80, 280, 30))
    thumb = np.zeros((30, 3))
    index = np.stack([np.cos(ang), np.sin(ang), np.zeros(30)], axis=1) * 0.005
    assert gripper_flipped(thumb, index)
    assert not gripper_flipped(thumb, index[:1].repeat(30, 0))  # a still line near 170 deg fits either way


def test_a_docking_module_is_pressed_only_once_aligned():
    # predicted touch presses elsewhere, with hysteresis
    assert anchored_press(False, aligned=False, docking=False, kpa=5.0, demonstrated_kpa=10.0)
    assert not anchored_press(False, aligned=False, docking=False, kpa=0.2, demonstrated_kpa=10.0)
    # docking: the same touch does not push the held module onto the board short of its target ...
    assert not anchored_press(True, aligned=False, docking=True, kpa=5.0, demonstrated_kpa=10.0)
    # ... the aligned mate does, touch or not
    assert anchored_press(False, aligned=True, docking=True, kpa=0.0, demonstrated_kpa=10.0)
