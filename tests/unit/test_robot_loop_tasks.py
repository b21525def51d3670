"""`xm eval --execute --task NAME`: the robot loop of every task with one, the learned policy alone
beside the anchored one on validation and held-out seeds, the carry tasks' anchors and loop."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

import evaluation.robot_eval as re_
from evaluation.anchors import pinch
from evaluation.carry import CarryAnchors, CarryState, carry_horizon, mine_carry_anchors, over_area
from evaluation.evaluate import main as eval_main
from evaluation.execute_carry import CARRY_TASKS, execute_carry
from evaluation.wipe_diagnosis import path_stats
from learning.ours import Ours
from learning.presets import preset
from services.world.tasks import TASKS
from services.world.teacher import generate_demo
from shared.demo import HAND_NAMES


def _demos(task: str, n: int) -> list:
    out = []
    for i in range(n):
        d = generate_demo(task, i, tactile_hand=HAND_NAMES[i % 2], grasp_hand=HAND_NAMES[i % 2], index=i)
        d.meta["split"] = "train"
        out.append(d)
    return out


def test_every_task_but_the_bottle_has_a_robot_loop_and_the_bottle_says_why(capsys):
    assert set(re_.LOOP_TASKS) == {"assembly", "latch", "pick_place", "wiping"}
    assert set(TASKS) - set(re_.LOOP_TASKS) == set(re_.NO_LOOP)  # every task without a loop has its reason
    assert eval_main(["--task", "bottle", "--execute", "--teacher"]) == 2
    err = capsys.readouterr().err
    assert "no robot loop" in err and "thread" in err and "pick_place" in err


def test_a_net_of_another_task_is_refused(tmp_path, capsys):
    torch.set_num_threads(1)
    model = Ours(preset("single_state", hidden=(16,), steps=1, batch=8, eval_every=10 ** 6))
    model.fit(_demos("pick_place", 1), progress=False)
    model.save(str(tmp_path / "p.pt"))
    assert eval_main(["--execute", "--task", "wiping", "--checkpoint", str(tmp_path / "p.pt"), "--out",
                      str(tmp_path), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "box/top" in err and "sponge/handle" in err


def test_execute_reports_the_learned_policy_beside_the_anchored_one_per_seed(tmp_path, monkeypatch):
    calls = []

    def fake(model, task, seed, demo, anchors, feedback, catch_m, recon=None, start_hands=None):
        calls.append((seed, demo, anchors is not None))
        return {"success": anchors is not None and demo != 10}  # anchored: all but layout 10

    monkeypatch.setattr(re_, "run_layout", fake)
    monkeypatch.setattr(re_, "anchors_for", lambda *a, **k: CarryAnchors("box/top", np.zeros(3), 0.05, 40.0))
    assert eval_main(["--execute", "--task", "pick_place", "--teacher", "--layouts", "3", "--held-out-seeds", "2",
                      "--out", str(tmp_path), "--no-progress"]) == 0
    # pick_place: 10 training demonstrations, the validation layouts start at 10
    assert calls == [(s, d, a) for s in (0, 2) for a in (False, True) for d in (10, 11, 12)]
    report = json.loads((tmp_path / "execute.json").read_text())
    rows = {(r["seed"], r["variant"]): r for r in report["rows"]}
    assert rows[0, "learned"]["successes"] == 0 and rows[0, "anchored"]["successes"] == 2
    assert rows[2, "anchored"]["layouts"] == "held-out" and rows[0, "learned"]["layouts"] == "validation"
    md = (tmp_path / "execute.md").read_text()
    assert "| seed 0 (validation) | 0 / 3 (0 %) | 2 / 3 (67 %) |" in md
    assert "| seed 2 (held-out) | 0 / 3 (0 %) | 2 / 3 (67 %) |" in md
    calls.clear()
    assert eval_main(["--execute", "--task", "pick_place", "--teacher", "--layouts", "1", "--no-anchors",
                      "--out", str(tmp_path), "--no-progress"]) == 0
    assert calls == [(0, 10, False)]


def test_carry_anchors_are_mined_from_the_demonstrations():
    a = mine_carry_anchors("pick_place", _demos("pick_place", 2))
    assert a.grasp_point == "box/top" and a.place_point == "box/bottom" and a.place_target == "plate/center"
    assert np.linalg.norm(a.place_offset) < 0.03 and a.grasp_kpa > 0 and 0.03 < a.grasp_width_m < 0.08
    w = mine_carry_anchors("wiping", _demos("wiping", 2))
    assert w.grasp_point == "sponge/handle" and w.contact_point == "sponge/bottom"
    assert 5.0 < w.press_n < 7.5  # the teacher presses 5.5-7 N, wavering by up to 0.5 N


def _horizon(pinch_at: np.ndarray, samples: int = 5) -> np.ndarray:
    """A horizon (S, 42 + 4, 3) whose left hand's thumb (4) and index (8) tips straddle ``pinch_at``."""
    h = np.zeros((samples, 46, 3))
    h[:, :21] = pinch_at
    h[:, 4] -= [0.01, 0, 0]
    h[:, 8] += [0.01, 0, 0]
    return h


def test_reaching_pulls_the_pinch_onto_the_grasp_point_from_above():
    names = ["box/top", "box/bottom", "plate/center", "plate/c0"]
    objects = np.array([[0.0, 0.1, 0.05], [0.0, 0.1, 0.0], [0.0, -0.1, 0.005], [0.0, -0.16, 0.005]])
    a = CarryAnchors("box/top", np.zeros(3), 0.05, 40.0, "box/bottom", "plate/center", np.zeros(3))
    near = _horizon(np.array([0.01, 0.1, 0.05]))  # 1 cm beside the box's top: within the full pull
    pads_over = np.array([0.0, 0.1, 0.1])
    out = carry_horizon(near, 0, a, objects, names, CarryState(), pads_over, depth=0.025)
    np.testing.assert_allclose(pinch(out[:, :21]), [[0.0, 0.1, 0.025]] * 5, atol=1e-9)  # the robot's depth
    far = _horizon(np.array([0.3, 0.1, 0.05]))  # 30 cm away: left as the policy put it
    np.testing.assert_allclose(carry_horizon(far, 0, a, objects, names, CarryState(), pads_over), far)
    pads_beside = np.array([0.05, 0.1, 0.1])  # the pads not yet over it: kept 15 mm above it
    out = carry_horizon(near, 0, a, objects, names, CarryState(), pads_beside)
    assert np.allclose(pinch(out[:, :21])[:, :2], [0.0, 0.1]) and np.allclose(pinch(out[:, :21])[:, 2], 0.065)


def test_holding_sets_the_box_on_the_plate_and_presses_the_pad_onto_the_area_only_over_it():
    names = ["box/top", "box/bottom", "plate/center"]
    objects = np.array([[0.0, 0.0, 0.10], [0.0, 0.0, 0.05], [0.02, -0.1, 0.005]])
    a = CarryAnchors("box/top", np.zeros(3), 0.05, 40.0, "box/bottom", "plate/center", np.zeros(3))
    pads = np.array([0.0, 0.0, 0.10])
    h = _horizon(np.array([0.0, -0.1, 0.08]))  # carrying the box 2 cm beside the plate's centre, 2.5 cm up
    out = carry_horizon(h, 0, a, objects, names, CarryState(held=True), pads)
    # the box's bottom, carried with the pads, lands on the plate's centre
    np.testing.assert_allclose(objects[1] + pinch(out[:, :21]) - pads, [objects[2]] * 5, atol=1e-9)
    names = ["sponge/bottom", "sponge/handle", "plate/a0", "plate/a1", "plate/a2", "plate/a3"]
    area = np.array([[-0.04, -0.025, 0.005], [0.04, -0.025, 0.005], [0.04, 0.025, 0.005], [-0.04, 0.025, 0.005]])
    objects = np.concatenate([[[0.0, 0.2, 0.02], [0.0, 0.2, 0.06]], area])
    w = CarryAnchors("sponge/handle", np.zeros(3), 0.02, 40.0, contact_point="sponge/bottom",
                     contact_target="plate/center", press_n=6.0)
    pads = np.array([0.0, 0.2, 0.052])
    h = _horizon(np.array([0.0, 0.2, 0.052]))
    h[:, :21] += np.linspace([0.0, -0.2, 0.0], [0.0, -0.2, 0.01], 5)[:, None]  # over the area, 15-25 mm up
    h[-1, :21] += [0.0, 0.0, 0.03]  # the last sample 5.5 cm above it: left alone
    out = carry_horizon(h, 0, w, objects, names, CarryState(held=True), pads, area)
    pad = objects[0] + pinch(out[:, :21]) - pads
    np.testing.assert_allclose(pad[:4, 2], 0.005, atol=1e-9)
    np.testing.assert_allclose(out[-1], h[-1])
    assert over_area(np.array([0.045, 0.0, 0.0]), area, 0.01) and not over_area(np.array([0.06, 0.0, 0.0]), area,
                                                                                   0.01)


@pytest.mark.parametrize("task", CARRY_TASKS)
def test_the_carry_loop_drives_the_robot_with_an_untrained_net(task):
    torch.set_num_threads(1)
    demos = _demos(task, 1)
    model = Ours(preset("single_state", hidden=(32, 32), steps=3, batch=16, eval_every=10 ** 6))
    model.fit(demos, progress=False)
    anchors = mine_carry_anchors(task, demos)
    r = execute_carry(model.policy, task, seed=0, demo=10, anchors=anchors, seconds=0.4)
    assert r.task == task and abs(r.seconds - 0.4) < 0.05 and np.isfinite(r.tracking_mm) and r.solves_rejected <= 4
    assert not r.success and r.object_motion_mm < 5.0 and np.isfinite(r.closest_mm)
    assert set(r.outcome) >= {"success"}


@pytest.mark.slow
@pytest.mark.parametrize("task", CARRY_TASKS)
def test_the_cell_does_the_carry_tasks_with_the_teachers_own_hands(task):
    """Everything but the policy, physically, with the anchors: pick_place succeeds; wiping grasps,
    carries and presses the sponge over the area, but its rigid pad chatters on the plate (the foam
    is not in MuJoCo) and wipes about three quarters of the area, short of the test's 90 %."""
    spec = TASKS[task]
    anchors = mine_carry_anchors(task, spec.protocol(0)[:spec.train])
    r = execute_carry(None, task, seed=0, demo=spec.train, anchors=anchors)
    assert r.closest_mm < 2.0 and r.object_motion_mm > 100.0, r
    if task == "pick_place":
        assert r.success and r.released and r.outcome["offset_mm"] < 10.0, r
    else:
        assert 0.6 < r.outcome["coverage"] < 0.9 and not r.success and r.max_press_n > 5.0, r


def test_the_wipe_diagnosis_reads_the_pads_height_and_path():
    d = generate_demo("wiping", 3, tactile_hand="left", grasp_hand="left")
    names = d.object_names
    r = path_stats(d.objects, names)
    assert r["near_steps"] > 150 and -4.5 < r["height_mm"] < -2.0  # the foam pressed 2-4.5 mm
    assert r["from_centre_mm"] < 30 and 5 < r["across_sd_mm"] < 10  # 12 mm circles over the area's centre
    raised = d.objects.copy()
    raised[:, [i for i, n in enumerate(names) if n.startswith("sponge/")], 2] += 0.012
    h = path_stats(raised, names)
    assert h["near_steps"] < 10 and 7.0 < h["height_mm"] < 10.0


def test_once_released_the_anchors_leave_the_policys_retreat_alone():
    names = ["box/top", "box/bottom", "plate/center"]
    objects = np.array([[0.0, 0.0, 0.055], [0.0, 0.0, 0.005], [0.0, 0.0, 0.005]])
    a = CarryAnchors("box/top", np.zeros(3), 0.05, 40.0, "box/bottom", "plate/center", np.zeros(3))
    h = _horizon(np.array([0.0, 0.02, 0.08]))  # 2 cm beside and above the box's top: a grasp pull would act
    assert not np.allclose(carry_horizon(h, 0, a, objects, names, CarryState(), np.zeros(3)), h)
    np.testing.assert_allclose(carry_horizon(h, 0, a, objects, names, CarryState(released=True), np.zeros(3)), h)
