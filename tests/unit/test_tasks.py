"""The task registry: every task's scripted teacher passes its world success test on a few layouts,
a deliberately wrong demonstration fails it, `xm eval --task` knows the tasks, and the force-decided
outcome reads predicted touch where a method has it and positions where it does not."""

from __future__ import annotations

from types import SimpleNamespace

import mujoco
import numpy as np
import pytest

from evaluation.evaluate import EvaluationError, evaluate
from evaluation.evaluate import main as eval_main
from evaluation.task_measure import task_measure
from services.world import latch, wiping
from services.world.sim import WorldSim
from services.world.tasks import TASKS, UnknownTaskError, demo_outcome, outcome, task
from services.world.teacher import KPA_PER_N, generate_demo
from shared.demo import TACTILE_REGIONS
from tests.unit.test_world_assembly import place_module_on_connector, push_and_lift

SEEDS = (0, 1, 2)


def test_the_registry_names_the_chapter_7_tasks_and_refuses_others():
    assert {"assembly", "latch", "wiping", "pick_place", "bottle"} <= set(TASKS)
    assert (task("wiping").train, task("pick_place").train, task("bottle").train) == (5, 10, 1)  # the thesis's
    with pytest.raises(UnknownTaskError, match="known tasks: .*wiping"):
        task("juggling")
    with pytest.raises(EvaluationError, match="known tasks"):
        evaluate(task="juggling", methods=["naive"], progress=False)


def test_xm_eval_lists_the_tasks_for_an_unknown_one(capsys):
    with pytest.raises(SystemExit) as exc:
        eval_main(["--task", "juggling"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert all(name in err for name in TASKS)


def test_execute_refuses_a_task_without_a_robot_loop(capsys):
    assert eval_main(["--task", "bottle", "--execute", "--teacher"]) == 2
    assert "no robot loop" in capsys.readouterr().err


@pytest.mark.parametrize("name", ["wiping", "latch", "bottle", "pick_place", "assembly"])
@pytest.mark.parametrize("seed", SEEDS)
def test_the_teachers_demonstrations_pass_the_world_success_test(name, seed):
    demo = generate_demo(name, 1000 * seed + seed, grasp_hand="left" if seed % 2 == 0 else "right")
    assert demo_outcome(demo)["success"], demo_outcome(demo)


def test_the_protocol_splits_train_and_validation_as_the_registry_says():
    demos = task("wiping").protocol(0)
    assert [d.meta["split"] for d in demos].count("train") == 5
    assert [d.meta["split"] for d in demos].count("validation") == 10
    assert all(d.meta["tactile_hand"] == d.meta["grasp_hand"] for d in demos)  # the glove on the wiping hand
    press_gloved = [d for d in task("latch").protocol(0)[:3] if d.meta["tactile_hand"] == d.meta["press_hand"]]
    assert len(press_gloved) == 2  # the press is what decides the latch


def _wiping(seed: int = 0):
    d = generate_demo("wiping", seed)
    return d, d.tactile.astype(float)


def test_wiping_with_too_little_or_too_much_pressure_fails():
    d, touch = _wiping()
    assert outcome("wiping", d.hands, d.objects, d.object_names, touch)["success"]
    weak = outcome("wiping", d.hands, d.objects, d.object_names, touch * 0.4)
    hard = outcome("wiping", d.hands, d.objects, d.object_names, touch * 2.5)
    assert not weak["success"] and weak["coverage"] == 0.0
    assert not hard["success"] and hard["peak_force_n"] > wiping.FORCE_BAND_N[1]


def test_wiping_beside_the_marked_area_fails():
    d, touch = _wiping(1)
    moved = d.objects.copy()
    plate = [i for i, n in enumerate(d.object_names) if n.startswith("plate/")]
    moved[:, plate, 0] += 0.1  # the plate 10 cm away from where the sponge wipes
    assert not outcome("wiping", d.hands, moved, d.object_names, touch)["success"]


def test_wiping_force_from_positions_is_the_foam_compression():
    d, touch = _wiping(2)
    from_touch = wiping.press_from_tactile(d.hands, d.objects, d.object_names, touch, KPA_PER_N, TACTILE_REGIONS)
    from_pos = wiping.press_from_positions(d.objects, d.object_names)
    pressing = from_touch > 3.0
    # the same force within the hand's 0.5 mm sway (1 N of foam), and zero off the plate
    assert np.abs(from_pos[pressing] - from_touch[pressing]).max() < 1.2
    assert from_pos[:50].max() == 0.0
    lifted = d.objects.copy()
    lifted[:, [d.object_names.index(n) for n in d.object_names if n.startswith("sponge/")], 2] += 0.004
    assert not outcome("wiping", d.hands, lifted, d.object_names)["success"]  # positions 4 mm up: no press


def test_a_latch_pressed_below_its_snap_force_or_crushed_fails():
    d = generate_demo("latch", 3, grasp_hand="right", tactile_hand="left")  # glove on the pressing hand
    touch = d.tactile.astype(float)
    assert outcome("latch", d.hands, d.objects, d.object_names, touch)["success"]
    under = outcome("latch", d.hands, d.objects, d.object_names, touch * 0.6)
    assert not under["latched"] and not under["success"]
    crushed = outcome("latch", d.hands, d.objects, d.object_names, touch * 2.5)
    assert crushed["peak_force_n"] > latch.DAMAGE_FORCE_N and not crushed["success"]
    raised = d.hands.copy()
    raised[..., 2] += 0.004  # force control closes 4 mm above the connector, not 8
    assert outcome("latch", raised, d.objects, d.object_names, touch)["success"]
    raised[..., 2] += 0.004
    assert not outcome("latch", raised, d.objects, d.object_names, touch)["latched"]


def test_a_cap_turned_with_a_slipping_grip_or_left_on_the_bottle_fails():
    d = generate_demo("bottle", 5, grasp_hand="right", tactile_hand="right")
    touch = d.tactile.astype(float)
    assert outcome("bottle", d.hands, d.objects, d.object_names, touch)["success"]
    slipping = outcome("bottle", d.hands, d.objects, d.object_names, touch * 0.5)  # < 3 N per finger
    assert slipping["turns"] == 0.0 and not slipping["success"]
    kept = d.objects.copy()
    lift = d.phase.index("lift")
    kept[lift:] = kept[lift]  # the cap stays on the bottle
    assert not outcome("bottle", d.hands, kept, d.object_names, touch)["success"]


def test_a_box_dropped_beside_the_plate_fails():
    d = generate_demo("pick_place", 4)
    assert outcome("pick_place", d.hands, d.objects, d.object_names)["success"]
    moved = d.objects.copy()
    box = [i for i, n in enumerate(d.object_names) if n.startswith("box/")]
    moved[-20:, box, 0] += 0.05
    assert not outcome("pick_place", d.hands, moved, d.object_names)["success"]


class _Touching:
    """A method whose neural simulation predicts the given touch."""

    def __init__(self, touch: np.ndarray) -> None:
        cfg = SimpleNamespace(tactile=True)
        self.policy = SimpleNamespace(cfg=cfg, initial_state=lambda start: {},
                                      roll=lambda state, steps: (None, touch[1:steps + 1], None))


def test_task_measure_reads_predicted_touch_where_a_method_has_it():
    d, touch = _wiping()
    outs = [(d.hands, d.objects)]
    with_touch = task_measure("wiping", _Touching(touch), outs, [d])
    blind = task_measure("wiping", SimpleNamespace(), outs, [d])
    assert with_touch["force_source"] == "predicted touch" and with_touch["mean"] == 1.0
    assert blind["force_source"] == "positions"
    weak = task_measure("wiping", _Touching(touch * 0.3), outs, [d])
    assert weak["mean"] == 0.0 and weak["success_rate"] == 0.0
    assert task_measure("pick_place", SimpleNamespace(), outs, [d]) is None  # no force-decided outcome
    bad = task_measure("wiping", SimpleNamespace(), [(d.hands * np.nan, d.objects)], [d])
    assert bad["rollouts"][0]["diverged"] and bad["mean"] == 0.0


def test_the_physical_world_counts_only_wiping_inside_the_force_band():
    sim = WorldSim("wiping", seed=0, width=32, height=24)
    sim.set_robot_mode("robot")
    m, data = sim.model, sim.data
    plate, sponge = sim._free["plate"], sim._free["sponge"]
    data.qpos[sponge:sponge + 3] = data.qpos[plate:plate + 3] + [0, 0, wiping.PLATE_TOP + 0.0005]
    data.qpos[sponge + 3:sponge + 7] = data.qpos[plate + 3:plate + 7]
    mujoco.mj_forward(m, data)
    body = m.body("sponge").id
    data.xfrc_applied[body, 2] = -1.0  # below the band: smears, wipes nothing
    sim.step(300)
    assert sim.task_success()["coverage"] == 0.0
    data.xfrc_applied[body, 2] = -6.0
    sim.step(300)
    pressed = sim.task_success()
    assert 0.0 < pressed["coverage"] < wiping.COVERED_FRACTION and not pressed["success"]  # one spot is not the area


@pytest.mark.parametrize("push_n, snaps", [(3.0, False), (2 * latch.LATCH_FORCE_N, True)])
def test_the_latch_snaps_only_at_its_force(push_n, snaps):
    sim = WorldSim("latch", seed=0, width=32, height=24)
    sim.start_demo(4)
    sim.set_robot_mode("robot")
    sim.step(50)
    place_module_on_connector(sim)
    sim.step(20)
    push_and_lift(sim, push_n)  # 3 N seats the assembly's connector (2 N), not the latch (5 N)
    assert (sim.seated_at is not None) == snaps
    assert sim.task_success()["success"] == snaps


@pytest.mark.parametrize("name", ["wiping", "latch", "bottle", "pick_place"])
def test_the_world_builds_each_task_and_its_objects_follow_the_teacher(name):
    sim = WorldSim(name, seed=1, width=32, height=24)
    sim.step(1500)  # 3 s: past every task's grasp
    names, points = sim.object_keypoints()
    state = sim.teacher.state(min(sim._applied_at, sim.teacher.duration))  # the script's last update
    assert names == sim.teacher.names
    np.testing.assert_allclose(points, state.keypoints, atol=1e-4)  # one physics step under gravity
