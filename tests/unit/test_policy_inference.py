"""The served policy: the compiled loop against the torch reference, the runner the node uses, the
neural simulation, guards against NaN and unusable checkpoints, and the naive fallback."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from evaluation.reference import follow_bodies, reference_roll, reference_step, rigid_fit
from learning.ours import Ours
from learning.presets import Recipe, preset
from services.policy import compiled as C
from services.policy.model import Policy, PolicyError
from services.policy.naive import NaiveReplay
from services.policy.runner import PolicyInputError, PolicyRunner, SceneObs, simulate
from shared.demo import Demo
from tests.unit.policy_demos import synthetic_demo

K = 4
# The compiled loop and the torch reference differ by float32 products summed in another order:
# relative 1e-4 of each quantity's scale (positions in m, tactile in kPa, memory in H std units).
RTOL, ATOL_SCALE = 1e-4, 1e-5


@pytest.fixture(scope="module")
def demos() -> list[Demo]:
    return [synthetic_demo(1, grasp="left"), synthetic_demo(2, grasp="right"), synthetic_demo(3, grasp="left")]


def tiny(recipe: Recipe, **kw) -> Recipe:
    return recipe.replace(**{"hidden": (32, 32), "steps": 3, "batch": 16, "eval_every": 10 ** 6} | kw)


@pytest.fixture(scope="module")
def trained(demos) -> Policy:
    torch.set_num_threads(1)
    method = Ours(tiny(preset("multimodal")))
    method.fit(demos[:2], progress=False)
    return method.policy


def untrained(demos, **changes) -> Policy:
    """A set-up, untrained net with its dynamics head at full size (an untrained J_D barely moves
    the objects)."""
    torch.set_num_threads(1)
    method = Ours(tiny(preset("multimodal", **changes)))
    method.setup(demos[:2])
    with torch.no_grad():
        method.net.head.weight.mul_(3.0)
    return method.policy


def hidden_state(policy: Policy, demo: Demo, seed: int = 0) -> dict:
    """A start state with points hidden on both hands and an object, and touch on both gloves (and a
    time window's history where the net has one)."""
    rng = np.random.default_rng(seed)
    state = policy.initial_state(demo)
    mask = np.ones(len(state["pos"]), bool)
    mask[[3, 21, 22, 44]] = False
    if "window_pos" in state:  # a history that moved, with points hidden in some of its samples
        seen = state["window_mask"].copy()
        seen[-2:, 5], seen[0, 30] = False, False
        state = dict(state, window_pos=state["window_pos"] + rng.normal(0, 0.01, state["window_pos"].shape),
                     window_mask=seen)
    return dict(state, mask=mask, tactile=rng.uniform(0, 30, (2, 6)), tmask=rng.random((2, 6)) < 0.5)


CASES = {"multimodal": {}, "no_tactile": {"tactile": False}, "single_state": {"tactile": False, "memory": False},
         "no_masks": {"masks": False}, "no_dynamics": {"dynamics": False}, "no_follow": {"follow_unobserved": False},
         "per_point_dynamics": {"body_dynamics": False},
         "time_window": {"tactile": False, "memory": False, "window": (8, 4, 2, 1, 1)},
         "window_multimodal": {"window": (2, 1, 1)}}


@pytest.mark.parametrize("case", sorted(CASES))
def test_compiled_rollout_equals_the_torch_reference(demos, case):
    """The one inference path (compiled.py) is the torch network's step (evaluation/reference.py)
    to RTOL: hidden points at the start and whatever the untrained net masks later, memory, tactile,
    at the sample period and at the optimizer's knots."""
    policy = untrained(demos, **CASES[case])
    state = hidden_state(policy, demos[2])
    for dt in (None, 0.05):
        # 12 steps: float32 rounding grows through an untrained net's memory gains (20-40x) over longer ones
        fast = policy.roll(state, 12, dt)
        slow = reference_roll(policy, state, 12, dt)
        assert np.abs(fast[0][-1] - state["pos"]).max() > 1e-3  # it moved
        for name, a, b in zip(("positions", "tactile", "memory"), fast, slow, strict=True):
            np.testing.assert_allclose(a, b, rtol=RTOL, atol=ATOL_SCALE * np.abs(b).max(initial=0.1),
                                       err_msg=f"{name}, dt {dt}")


@pytest.mark.parametrize("case", ["multimodal", "no_masks", "single_state", "time_window"])
def test_one_compiled_step_is_the_reference_step(demos, case):
    """Every field of the next state (positions, velocities, mask, tactile, memory, time)."""
    policy = untrained(demos, **CASES[case])
    state = hidden_state(policy, demos[2])
    fast, slow = [state], [state]
    for _ in range(3):
        fast.append(policy.step(fast[-1]))
        slow.append(reference_step(policy, slow[-1]))
    for a, b in zip(fast[1:], slow[1:], strict=True):
        assert a.keys() == b.keys()
        for key in b:
            x, y = np.asarray(a[key], float), np.asarray(b[key], float)
            np.testing.assert_allclose(x, y, rtol=RTOL, atol=ATOL_SCALE * np.abs(y).max(initial=1.0), err_msg=key)
    assert (fast[1]["mask"] != state["mask"]).any() or case == "no_masks"  # the net's own mask came through


def test_the_reference_switches_change_the_step(demos):
    """follow_unobserved and the dynamics weight act on the step, in the reference and compiled alike."""
    base = untrained(demos)
    state = hidden_state(base, demos[2])
    nxt = base.step(state)["pos"]
    for changes in ({"follow_unobserved": False}, {"w_dyn": 0.5}, {"max_speed": 0.01}):
        other = untrained(demos, **changes)
        moved = other.step(state)["pos"]
        assert np.abs(moved - nxt).max() > 1e-6, changes
        np.testing.assert_allclose(moved, reference_step(other, state)["pos"], rtol=RTOL, atol=1e-7)


def test_compiled_rollout_refuses_nan_and_compiles_once(demos):
    policy = untrained(demos)
    C.warm()
    state = policy.initial_state(demos[2])
    policy.roll(state, 3)
    assert len(C._rollout.signatures) == 1  # warm() compiled what the real call runs
    with torch.no_grad():
        policy.net.head.bias[0] = float("nan")
    with pytest.raises(PolicyError, match="NaN"):
        policy.roll(state, 3)
    with pytest.raises(PolicyError):
        policy.rollout(demos[2], 3)


def test_the_folded_copy_follows_weight_updates(trained, demos):
    state = trained.initial_state(demos[2])
    before = trained.step(state)["pos"]
    first = trained.net.trunk[0]
    with torch.no_grad():
        saved = first.weight.clone()
        first.weight.mul_(1.5)
    try:
        after = trained.step(state)["pos"]
        assert not np.allclose(after, before)
        np.testing.assert_allclose(after, reference_step(trained, state)["pos"], rtol=RTOL, atol=1e-7)
    finally:
        with torch.no_grad():
            first.weight.copy_(saved)


def scene_of(d: Demo, t: int) -> SceneObs:
    return SceneObs(d.hands[t].astype(float), d.hand_mask[t], d.objects[t].astype(float), d.object_mask[t],
                    d.tactile[t], d.tactile_mask[t])


def test_runner_steps_horizons_and_guards_nan(trained, demos):
    d = demos[2]
    runner = PolicyRunner(trained)
    with pytest.raises(PolicyInputError):
        runner.horizon(None, 5)
    bad = scene_of(d, 0)
    bad.hands[0, 3] = np.nan
    with pytest.raises(PolicyInputError):
        runner.step(bad)
    nxt = runner.step(scene_of(d, 0))
    assert nxt.shape == (42 + K, 3) and np.isfinite(nxt).all()
    occluded = scene_of(d, 1)
    occluded.hands[1, 5] = np.nan  # NaN later on: kept from the prediction, never propagated
    assert np.isfinite(runner.step(occluded)).all()
    plan = runner.horizon(scene_of(d, 2), 7)
    assert plan.shape == (7, 42 + K, 3) and np.isfinite(plan).all()
    assert runner.efforts.shape == (2, 6)


def test_horizon_at_the_optimizers_knots_integrates_over_the_longer_step(trained, demos):
    runner = PolicyRunner(trained)
    runner.step(scene_of(demos[2], 0))
    start, memory = runner.state["pos"].copy(), runner.state["H"].copy()
    fine = runner.horizon(None, 10)
    coarse = runner.horizon(None, 5, dt=2 * trained.dt)
    assert coarse.shape == (5, 42 + K, 3) and np.isfinite(coarse).all()
    # the first step reads the same network outputs, over twice the time
    np.testing.assert_allclose(coarse[0] - start, 2 * (fine[0] - start), atol=1e-9)
    assert np.abs(coarse[0] - start).max() > 1e-6
    np.testing.assert_array_equal(runner.state["H"], memory)  # a look-ahead leaves the memory alone


def test_simulate_follows_observed_objects(trained, demos):
    d = demos[2]
    roll = simulate(trained, d, 10, observed_objects=d.objects[:10])
    np.testing.assert_allclose(roll.objects[1:], d.objects[1:10], atol=1e-6)
    free = simulate(trained, d, 10)
    np.testing.assert_allclose(free.hands[:2], roll.hands[:2], atol=1e-12)  # the first step sees the same scene
    with pytest.raises(PolicyInputError):
        simulate(trained, d, 10, observed_objects=np.full((10, K, 3), np.nan))


def test_a_checkpoint_of_the_single_config_layout_is_refused(trained):
    old = trained.state()
    old["meta"] = {k: v for k, v in old["meta"].items() if k not in ("format", "model", "inference")}
    old["meta"]["config"] = '{"name": "multimodal", "velocity_input": false}'
    with pytest.raises(PolicyError, match="train it again"):
        Policy.from_state(old)


def test_rigid_fit_recovers_a_rigid_motion_and_stays_finite_on_a_line():
    rng = np.random.default_rng(1)
    p, w, vc = rng.normal(size=(6, 3)), rng.normal(size=3), rng.normal(size=3)
    v = vc + np.cross(w, p - p.mean(axis=0))
    _, vc_fit, w_fit = rigid_fit(v, p)
    np.testing.assert_allclose(vc_fit, vc, atol=1e-12)
    np.testing.assert_allclose(w_fit, w, atol=1e-6)
    line = np.outer(np.arange(3.0), [1.0, 0.0, 0.0])  # spin about the line is unobservable: none is invented
    _, _, w_line = rigid_fit(np.cross([0.0, 0.0, 1.0], line), line)
    np.testing.assert_allclose(w_line, [0.0, 0.0, 1.0], atol=1e-6)
    assert np.isfinite(rigid_fit(np.ones((4, 3)), np.zeros((4, 3)))[2]).all()


def test_unobserved_points_follow_the_rigid_motion_of_their_body():
    rng = np.random.default_rng(3)
    p = rng.normal(0, 0.05, (10, 3))
    bodies = np.array([0] * 6 + [1] * 4)
    vc, w = np.array([0.1, -0.2, 0.05]), np.array([0.0, 0.0, 2.0])  # body 0 translates and turns
    c = p[:6].mean(axis=0)
    v = np.zeros((10, 3))
    v[:6] = vc + np.cross(w, p[:6] - c)
    v[[2, 7]] = [5.0, 5.0, 5.0]  # untrained outputs of two unobserved points
    trusted = np.ones(10, bool)
    trusted[[2, 7]] = False
    out = follow_bodies(v, p, trusted, bodies)
    np.testing.assert_allclose(out[2], vc + np.cross(w, p[2] - c), atol=1e-9)  # back on body 0's motion
    np.testing.assert_allclose(out[7], 0.0, atol=1e-9)  # body 1 stands still
    np.testing.assert_array_equal(np.delete(out, [2, 7], 0), np.delete(v, [2, 7], 0))
    alone = follow_bodies(v, p, np.r_[np.ones(6, bool), np.zeros(4, bool)], bodies)
    np.testing.assert_array_equal(alone[6:], v[6:])  # nothing seen on body 1: outputs kept


def test_naive_plans_live_at_the_plan_spacing(demos):
    """The node's naive replay: chosen by the observed start, sampled at the plan's own dt."""
    naive = NaiveReplay()
    naive.fit(demos)
    start = np.concatenate([demos[1].hands[0].ravel(), demos[1].objects[0].ravel()]).astype(float)
    start[:63] = np.nan  # the left hand unobserved
    plan = naive.plan(start, 0.0, 4, 0.1)
    assert naive.chosen == 1
    np.testing.assert_allclose(plan[1, :126].reshape(2, 21, 3), demos[1].hands[5], atol=1e-6)  # 0.1 s = 5 samples
    later = naive.plan(start * 0, 0.5, 3, 0.1)  # mid-episode: not chosen again
    assert naive.chosen == 1
    np.testing.assert_allclose(later[0, :126].reshape(2, 21, 3), demos[1].hands[25], atol=1e-6)
