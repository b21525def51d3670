"""Chapter-7 policy: data augmentation, the consistency solve, every config switch, checkpoints, guards."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from services.policy import dataset as D
from services.policy.consistency import ConsistencySolver, follow_bodies
from services.policy.network import Layout, PolicyConfig, config_changes, preset
from services.policy.ours import Ours, PolicyError
from services.policy.reservoir import Reservoir
from services.policy.simulate import PolicyInputError, PolicyRunner, SceneObs, simulate
from shared.demo import Demo

K = 4


def synthetic_demo(seed: int, T: int = 40, grasp: str = "left", glove: str = "left") -> Demo:
    """A hand reaching to an object and carrying it; tactile on while carrying (tests only)."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 1, T)[:, None]
    obj0 = np.array([0.05, 0.0, 0.0]) + rng.normal(0, 0.02, 3)
    shape = rng.normal(0, 0.03, (21, 3))
    g = 0 if grasp == "left" else 1
    hands = np.zeros((T, 2, 21, 3))
    start = np.array([[-0.1, 0.3, 0.15], [-0.1, -0.3, 0.15]])
    reach = np.clip(2 * t, 0, 1)
    carry = np.clip(2 * t - 1, 0, 1)
    pinch = start[g] + (obj0 - start[g]) * reach + np.array([0.0, 0.0, 0.1]) * carry
    hands[:, g] = pinch[:, None] + shape
    hands[:, 1 - g] = start[1 - g] + shape + 0.01 * np.sin(6 * t)[:, None]
    local = rng.normal(0, 0.01, (K, 3))
    objects = np.where(carry[:, None] > 0, pinch[:, None], obj0) + local
    tactile = np.zeros((T, 2, 6))
    tactile[:, g, :2] = 20.0 * (carry > 0)
    tmask = np.zeros((T, 2, 6), np.uint8)
    tmask[:, 0 if glove == "left" else 1] = 1
    hmask = np.ones((T, 2, 21), np.uint8)
    hmask[5:8, 0, 3] = 0
    return Demo(dt=0.02, hands=hands.astype(np.float32), hand_mask=hmask, object_names=[f"o/{i}" for i in range(K)],
                objects=objects.astype(np.float32), object_mask=np.ones((T, K), np.uint8),
                tactile=(tactile * tmask).astype(np.float32), tactile_mask=tmask, phase=["x"] * T,
                meta={"task": "synthetic", "demo": seed, "grasp_hand": grasp, "tactile_hand": glove})


@pytest.fixture(scope="module")
def demos():
    return [synthetic_demo(1), synthetic_demo(2, grasp="right", glove="left"), synthetic_demo(3)]


def tiny(cfg: PolicyConfig, **kw) -> PolicyConfig:
    return cfg.replace(**{"hidden": (32, 32), "steps": 3, "batch": 16, "eval_every": 10 ** 6, "seq_len": 4,
                          "candidates": 1} | kw)


def test_mirror_swaps_hands_and_preserves_distances(demos):
    d = demos[0]
    m = D.mirror(d)
    assert m.meta["grasp_hand"] == "right" and m.meta["tactile_hand"] == "right"
    np.testing.assert_allclose(m.hands[:, 1, :, 1], -d.hands[:, 0, :, 1])
    np.testing.assert_array_equal(m.tactile[:, 1], d.tactile[:, 0])
    dist = np.linalg.norm(d.hands[:, 0, 8] - d.objects[:, 0], axis=-1)
    np.testing.assert_allclose(np.linalg.norm(m.hands[:, 1, 8] - m.objects[:, 0], axis=-1), dist, rtol=1e-5)
    assert D.mirror(m).meta["grasp_hand"] == "left"


def test_rotation_about_gravity_preserves_distances_and_heights():
    p = np.random.default_rng(0).normal(size=(5, 3))
    r = D.rotate_z(p, 0.7)
    d = np.linalg.norm(p[:, None] - p[None], axis=-1)
    np.testing.assert_allclose(np.linalg.norm(r[:, None] - r[None], axis=-1), d, atol=1e-12)
    np.testing.assert_allclose(r[:, 2], p[:, 2])
    assert not np.allclose(r, p)


def test_reservoir_components_equal_rerun_on_rotated_velocities():
    rng = np.random.default_rng(1)
    v, mask = rng.normal(size=(30, 5, 3)), rng.random((30, 5)) > 0.2
    res = Reservoir(5, 8, 0.95, seed=2)
    a = 1.1
    np.testing.assert_allclose(Reservoir.rotated(res.components(v, mask), a), res.run(D.rotate_z(v, a), mask),
                               atol=1e-9)


def test_reservoir_with_fixed_periods_draws_only_its_eigenbasis():
    spectra = []
    for seed in (0, 1):
        res = Reservoir(5, 8, 0.9, seed=seed, periods=(4.0, 32.0))
        np.testing.assert_allclose(res.W_R @ res.W_R.T, 0.81 * np.eye(8), atol=1e-12)
        ev = np.linalg.eigvals(res.W_R)
        np.testing.assert_allclose(np.abs(ev), 0.9)
        spectra.append(np.sort(2 * np.pi / np.abs(np.angle(ev))))
    np.testing.assert_allclose(spectra[0], np.repeat([4.0, 8.0, 16.0, 32.0], 2))
    np.testing.assert_allclose(spectra[0], spectra[1])
    plain = [np.sort(np.abs(np.angle(np.linalg.eigvals(Reservoir(5, 8, 0.9, seed=s).W_R)))) for s in (0, 1)]
    assert not np.allclose(plain[0], plain[1])  # a plain random orthogonal W_R: the periods change with the draw


def test_lag_noise_shows_the_scene_as_it_was_earlier_and_corrects_towards_now(demos):
    method = Ours(tiny(preset("multimodal"), lag_noise=1.0, lag_s=0.1))
    data = method.setup(demos[:2])
    b = method.make_batch(data, np.random.default_rng(0), 64)
    R = b["pos"] - b["clean_pos"]
    lagged = data.step_index[b["index"]] > 0  # a first step has no earlier scene: ordinary noise
    for k in np.flatnonzero(lagged)[:8]:
        i, a = b["index"][k], b["angle"][k]
        back = [(D.rotate_z(data.pos[i - j] - data.pos[i], a), data.mask[i] & data.mask[i - j])
                for j in range(1, min(6, data.step_index[i] + 1))]  # up to 0.1 s back, within the demonstration
        assert any(np.allclose(R[k][seen], r[seen]) for r, seen in back)
    gain = method.correction_gain(b["scale"], data.dt)[:, None, None]
    np.testing.assert_allclose(b["target_vel"], b["next_vel"] - R * gain)


def test_reservoir_seed_draws_the_reservoir_apart_from_the_weights(demos):
    nets = {}
    for seed, reservoir_seed in ((0, -1), (1, -1), (1, 0)):
        method = Ours(tiny(preset("multimodal"), seed=seed, reservoir_seed=reservoir_seed))
        method.setup(demos[:2])
        nets[seed, reservoir_seed] = method
    own, other, mixed = nets[0, -1], nets[1, -1], nets[1, 0]
    np.testing.assert_array_equal(mixed.reservoir.W_R, own.reservoir.W_R)  # draw 0's reservoir ...
    np.testing.assert_array_equal(mixed.reservoir.W_I, own.reservoir.W_I)
    assert not np.allclose(other.reservoir.W_R, own.reservoir.W_R)
    for a, b in zip(mixed.net.trunk.parameters(), other.net.trunk.parameters(), strict=True):
        torch.testing.assert_close(a, b)  # ... under draw 1's initial weights


def test_config_changes_are_typed_like_their_fields_and_bad_ones_named():
    got = config_changes(["reservoir_periods=0.25,8", "hidden=64,32", "mirror=false", "lr=3e-4", "steps=10"])
    assert got == {"reservoir_periods": (0.25, 8.0), "hidden": (64, 32), "mirror": False, "lr": 3e-4, "steps": 10}
    assert preset("multimodal", **got).hidden == (64, 32)
    for bad, says in (("colour=red", "'colour=red'"), ("steps", "'steps'"), ("steps=ten", "not a int"),
                      ("mirror=maybe", "not a bool"), ("name=x", "'name=x'"), ("candidates=0", "at least 1"),
                      ("candidate_fraction=1.5", "in \\(0, 1\\]")):
        with pytest.raises(ValueError, match=says):
            config_changes([bad])


def test_frame_yaw_recovers_the_turn_of_the_widest_object():
    rng = np.random.default_rng(3)
    small, wide = rng.normal(0, 0.005, (2, 3)), rng.normal(0, 0.03, (4, 3))
    idx, ref = D.reference_object(["a/0", "a/1", "b/0", "b/1", "b/2", "b/3"], np.concatenate([small, wide]))
    assert idx.tolist() == [2, 3, 4, 5]
    for turn in (0.0, 0.4, -2.9):
        moved = D.rotate_z(wide, turn) + [0.1, -0.2, 0.05]
        assert float(D.frame_yaw(moved, ref)) == pytest.approx(turn, abs=1e-9)
    with pytest.raises(D.DatasetError):
        D.reference_object(["a/0"], small[:1])


def turned(d: Demo, angle: float, shift: tuple = (0.03, -0.02, 0.0)) -> Demo:
    return Demo(**{**d.__dict__, "hands": (D.rotate_z(d.hands.astype(float), angle) + shift).astype(np.float32),
                   "objects": (D.rotate_z(d.objects.astype(float), angle) + shift).astype(np.float32)})


@pytest.mark.parametrize("canonical", [True, False])
def test_canonical_frame_makes_the_policy_turn_with_the_scene(demos, canonical):
    """7.2.4 by construction: a scene turned about gravity (and shifted) gives the turned rollout;
    the augmented net only approximates that."""
    torch.set_num_threads(1)
    method = Ours(tiny(preset("multimodal"), canonical_frame=canonical))
    method.fit(demos[:2], progress=False)
    angle, shift = 0.9, np.array([0.03, -0.02, 0.0])
    hands, objects = method.rollout(demos[2], 10)
    hands_t, objects_t = method.rollout(turned(demos[2], angle, tuple(shift)), 10)
    gap = max(np.abs(D.rotate_z(hands, angle) + shift - hands_t).max(),
              np.abs(D.rotate_z(objects, angle) + shift - objects_t).max())
    assert (gap < 1e-4) if canonical else (gap > 1e-3)
    assert np.abs(hands[-1] - hands[0]).max() > 1e-3  # the rollout moves at all


def test_goal_body_is_the_unmoved_object_the_pinch_reaches_next():
    T, dt = 200, 0.02
    t = np.arange(T) * dt
    pos = np.zeros((T, 44, 3))
    pos[:, 21:42] = [0.0, -0.4, 0.2]  # the other hand stays away
    obj = np.array([0.1, 0.0, 0.0])
    pinch = obj + np.array([0.3, 0.0, 0.0]) * np.clip(1 - t / 2.0, 0, 1)[:, None]  # reaches it at 2 s
    pinch[:, 2] += np.clip(t - 2.5, 0, None) * 0.1  # lifts it from 2.5 s
    pos[:, :21] = pinch[:, None]
    pos[:, 42] = pos[:, 43] = obj
    pos[:, 42:44, 2] += np.clip(t - 2.5, 0, None)[:, None] * 0.1
    goal = D.goal_bodies(pos, np.ones((T, 44), bool), np.array([0, 0]), dt)
    assert (goal[:, 1] == -1).all()
    # 5 cm from the object at 1.67 s: a goal from 0.67 s (1 s ahead) until the object moves (2.55 s)
    assert (goal[:30, 0] == -1).all() and (goal[36:125, 0] == 0).all() and (goal[130:, 0] == -1).all()


def test_goal_relative_noise_moves_the_hand_target_with_its_goal_object(demos):
    cfg = tiny(preset("no_tactile"), goal_relative=True, canonical_frame=False, memory=False)
    method = Ours(cfg)
    data = method.setup(demos[:2])
    b = method.make_batch(data, np.random.default_rng(0), 64)
    R = b["pos"] - b["clean_pos"]
    shift = np.where((b["goal"] == 0)[:, :, None], R[:, 42:].mean(1)[:, None], 0.0)  # one object body
    want = b["next_vel"].copy()
    want -= R * cfg.noise_gain
    want[:, :42] += np.repeat(shift, 21, axis=1) * cfg.noise_gain
    assert (b["goal"] == 0).any() and (b["goal"] == -1).any()
    np.testing.assert_allclose(b["target_vel"], want, atol=1e-9)


def test_correction_speed_raises_the_gain_only_for_small_noise():
    method = Ours(preset("no_tactile", correction_speed=0.05))
    gain = method.correction_gain(np.array([1e-4, 0.002, 0.00625, 0.05]), 0.02)
    np.testing.assert_allclose(gain, [50.0, 25.0, 8.0, 8.0])  # capped at 1/dt, f_n = 8/s for large noise
    np.testing.assert_allclose(Ours(preset("no_tactile")).correction_gain(np.array([1e-4, 0.05]), 0.02), 8.0)


def test_body_dynamics_shares_j_within_each_rigid_object():
    method = Ours(preset("no_tactile", body_dynamics=True))
    method.object_names = ["board/a", "board/b", "cam/lens", "cam/cable", "cam/conn"]
    J = np.random.default_rng(0).normal(size=(5, 2))
    pooled = method.body_pooled(J)
    np.testing.assert_allclose(pooled[:2], np.broadcast_to(J[:2].mean(0), (2, 2)))
    np.testing.assert_allclose(pooled[2:], np.broadcast_to(J[2:].mean(0), (3, 2)))
    torch_pooled = method.body_pooled(torch.as_tensor(J[None], dtype=torch.float32))[0].numpy()
    np.testing.assert_allclose(torch_pooled, pooled, atol=1e-6)
    method.cfg = method.cfg.replace(body_dynamics=False)
    np.testing.assert_array_equal(method.body_pooled(J), J)


def test_body_dynamics_trains_j_where_the_holding_hand_hides_its_pinch():
    """The thumb of the carrying hand is hidden while it carries: without the stand-in velocity no
    sample where the object moves reaches the J_D loss."""
    hidden = []
    for d in (synthetic_demo(1), synthetic_demo(3)):
        hm = d.hand_mask.copy()
        hm[len(hm) // 2:, 0, 4] = 0
        hidden.append(Demo(**{**d.__dict__, "hand_mask": hm}))
    dyn = {}
    for body in (False, True):
        method = Ours(tiny(preset("no_tactile"), body_dynamics=body, memory=False, denoise=False))
        data = method.setup(hidden)
        with torch.no_grad():
            method.net.head.weight[method.net.slices["J"]] = 0.0
            method.net.head.bias[method.net.slices["J"]] = 0.0
        _, parts = method.loss(method.make_batch(data, np.random.default_rng(0), 512))
        dyn[body] = parts["dyn"]
    assert dyn[False] < 1e-9 < 0.1 < dyn[True]


def test_hand_sampling_is_sixty_forty():
    left = np.array([True] * 10 + [False] * 30)
    p = D.hand_weights(left, 0.6)
    assert p[left].sum() == pytest.approx(0.6) and p.sum() == pytest.approx(1.0)
    np.testing.assert_allclose(D.hand_weights(np.ones(4, bool)), 0.25)


def test_split_by_demonstration(demos):
    splits = ("train", "validation", "train")
    tagged = [Demo(**{**d.__dict__, "meta": {**d.meta, "split": s}}) for d, s in zip(demos, splits, strict=True)]
    tr, va = D.split_demos(tagged)
    assert [d.meta["demo"] for d in tr] == [1, 3] and [d.meta["demo"] for d in va] == [2]


def test_consistency_solve_is_exact_integral_when_unconstrained():
    lay = Layout(K)
    rng = np.random.default_rng(0)
    prev, v = rng.normal(0, 0.1, (lay.P, 3)), rng.normal(0, 0.3, (lay.P, 3))
    s = ConsistencySolver(lay, 0.02, w_pair=0.0, w_dyn=0.0)
    nxt = s.positions(prev, s.velocities(v[:42], v[42:], None), None)
    np.testing.assert_allclose((nxt - prev) / 0.02 - v, 0.0, atol=1e-12)  # 7.5 exactly
    # consistent pair predictions leave the exact solution unchanged; inconsistent ones pull anchors
    s2 = ConsistencySolver(lay, 0.02, w_pair=5.0)
    a = nxt[lay.anchors]
    pairs = a[lay.pair_j] - a[lay.pair_i]
    np.testing.assert_allclose(s2.positions(prev, v, pairs), nxt, atol=1e-10)
    moved = s2.positions(prev, v, pairs + 0.01)
    assert np.abs(moved - nxt).max() > 1e-4
    np.testing.assert_allclose(np.delete(moved, lay.anchors, 0), np.delete(nxt, lay.anchors, 0))


def test_dynamics_constraint_moves_objects_with_the_pinch():
    lay = Layout(K)
    s = ConsistencySolver(lay, 0.02, w_pair=0.0, w_dyn=1.0)
    vh = np.zeros((42, 3))
    vh[[4, 8]] = [0.1, 0.0, 0.0]
    J = np.zeros((K, 2))
    J[:, 0] = 1.0
    v = s.velocities(vh, np.zeros((K, 3)), J)
    np.testing.assert_allclose(v[42:], [[0.05, 0.0, 0.0]] * K)  # halfway: equal weights


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


def test_memory_solve_is_least_squares_of_7_9_and_7_10():
    Hp, Hprev, dH = np.array([1.0]), np.array([0.0]), np.array([10.0])
    for w in (1.0, 0.01):
        H = ConsistencySolver.memory(Hp, Hprev, dH, 0.02, w)
        grad = w * (H - Hp) + (H - Hprev - dH * 0.02)
        np.testing.assert_allclose(grad, 0.0, atol=1e-12)
    assert abs(ConsistencySolver.memory(Hp, Hprev, dH, 0.02, 0.01) - 0.2) < 0.01  # mostly the integrated rate


SWITCHES = {
    "multimodal": {},
    "no_tactile": {"tactile": False},
    "single_state": {"tactile": False, "memory": False},
    "no_denoise": {"denoise": False},
    "no_masks": {"masks": False},
    "no_pairs": {"pair_outputs": False},
    "no_dynamics": {"dynamics": False},
    "tactile_model": {"tactile_model": True},
    "object_model": {"object_model": True},
    "recurrent": {"recurrent": True, "memory": False},
    "recurrent_memory": {"recurrent": True},
    "no_rotate_no_mirror": {"rotate": False, "mirror": False},
    "canonical_goal_speed": {"canonical_frame": True, "goal_relative": True, "correction_speed": 0.05},
    "body_dynamics": {"body_dynamics": True},
    "rigid_objects": {"rigid_objects": True},
}


@pytest.mark.parametrize("switch", sorted(SWITCHES))
def test_every_switch_trains_and_rolls_out_finite(demos, switch):
    torch.set_num_threads(1)
    cfg = tiny(preset("multimodal"), **SWITCHES[switch])
    method = Ours(cfg)
    method.fit(demos[:2], progress=False)
    assert len(method.losses) == 3 and np.isfinite(method.losses).all()
    hands, objects = method.rollout(demos[2], 12)
    assert hands.shape == (12, 2, 21, 3) and objects.shape == (12, K, 3)
    assert np.isfinite(hands).all() and np.isfinite(objects).all()
    np.testing.assert_allclose(hands[0], demos[2].hands[0], atol=1e-6)


def test_training_reduces_the_loss(demos):
    torch.set_num_threads(1)
    method = Ours(preset("single_state", hidden=(64, 64), steps=150, batch=64, eval_every=10 ** 6, lr=3e-3))
    method.fit(demos[:2], progress=False)
    assert np.mean(method.losses[-20:]) < 0.5 * np.mean(method.losses[:20])


def test_checkpoint_round_trip_weights_only(demos, tmp_path):
    torch.set_num_threads(1)
    from services.policy.train import train

    res = train(tiny(preset("multimodal")), demos[:2], demos[2:], tmp_path / "run", progress=False)
    assert res.checkpoint.exists() and (tmp_path / "run" / "loss.png").exists()
    ckpt = torch.load(res.checkpoint, weights_only=True)
    again = Ours.from_state(ckpt)
    assert again.cfg == res.method.cfg
    h1, o1 = res.method.rollout(demos[2], 10)
    h2, o2 = again.rollout(demos[2], 10)
    np.testing.assert_allclose(h2, h1, atol=1e-6)
    np.testing.assert_allclose(o2, o1, atol=1e-6)


@pytest.fixture(scope="module")
def trained(demos):
    torch.set_num_threads(1)
    method = Ours(tiny(preset("multimodal")))
    method.fit(demos[:2], progress=False)
    return method


def test_nan_network_output_raises(trained, demos):
    with torch.no_grad():
        bias = trained.net.head.bias.clone()
        trained.net.head.bias.fill_(float("nan"))
    try:
        with pytest.raises(PolicyError):
            trained.rollout(demos[2], 3)
    finally:
        with torch.no_grad():
            trained.net.head.bias.copy_(bias)


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
    with pytest.raises(PolicyInputError):
        simulate(trained, d, 10, observed_objects=np.full((10, K, 3), np.nan))


FOLD_CASES = {
    "multimodal": {},
    "no_tactile": {"tactile": False},
    "single_state": {"tactile": False, "memory": False},
    "velocity_and_phase_inputs": {"velocity_input": True, "phase_input": True},
    "pair_constraint_on": {"w_pair": 1.0},
    "no_masks": {"masks": False},
}


@pytest.mark.parametrize("case", sorted(FOLD_CASES))
def test_folded_forward_equals_the_network(demos, case):
    """The folded batch-one pass (P4) is the same function as PolicyNet, masked points included."""
    torch.set_num_threads(1)
    method = Ours(tiny(preset("multimodal", **FOLD_CASES[case])))
    method.setup(demos[:2])
    method.net.eval()
    assert method.folded() is not None
    rng = np.random.default_rng(0)
    state = method.initial_state(demos[2])
    P = len(state["pos"])
    for masked in ([], [0], [4, 8, 44], [0, 20, 21, 42, 43, 44, 45], list(range(0, P, 2))):
        s = dict(state, pos=state["pos"] + rng.normal(0, 0.02, (P, 3)), vel=rng.normal(0, 0.1, (P, 3)),
                 tactile=rng.uniform(0, 30, (2, 6)), tmask=rng.random((2, 6)) < 0.5, t=0.7)
        mask = np.ones(P, bool)
        mask[masked] = False
        s["mask"] = mask
        fast, plain = method.network_outputs(s), method.network_outputs(s, fold=False)
        assert "pairs" in fast or FOLD_CASES[case].get("w_pair", 0.0) == 0.0
        for key, value in fast.items():
            np.testing.assert_allclose(value, plain[key], rtol=1e-4, atol=1e-4 * np.abs(plain[key]).max(),
                                       err_msg=f"{key} with points {masked} masked")


def test_folded_copy_follows_weight_updates(trained, demos):
    state = trained.initial_state(demos[2])
    before = trained.network_outputs(state)["vel"]
    first = trained.net.trunk[0]
    with torch.no_grad():
        saved = first.weight.clone()
        first.weight.mul_(1.5)
    try:
        after = trained.network_outputs(state)["vel"]
        assert not np.allclose(after, before)
        np.testing.assert_allclose(after, trained.network_outputs(state, fold=False)["vel"], rtol=1e-4, atol=1e-5)
    finally:
        with torch.no_grad():
            first.weight.copy_(saved)


def test_folded_copy_follows_a_fused_optimizer_step(demos):
    # the fused step does not bump version counters: the training step must drop the folded copy,
    # or every selection rollout after the first scores stale weights
    from services.policy.train import make_optimizer, optimizer_step

    method = Ours(tiny(preset("no_tactile"), lr=1e-2))
    data = method.setup(demos[:2])
    state = method.initial_state(demos[2])
    method.net.eval()
    before = method.network_outputs(state)["vel"]
    opt = make_optimizer(method.net, method.cfg.lr)
    method.net.train()
    loss, _ = method.loss(method.make_batch(data, np.random.default_rng(0), 16))
    optimizer_step(method, opt, loss)
    method.net.eval()
    after = method.network_outputs(state)["vel"]
    assert not np.allclose(after, before)
    np.testing.assert_allclose(after, method.network_outputs(state, fold=False)["vel"], rtol=1e-4, atol=1e-5)


def test_ema_weights_are_what_is_scored_and_kept(demos, monkeypatch):
    from services.policy import train as T

    seen = []  # the weights before the first step, then after each
    step = T.optimizer_step

    def recording(method, opt, loss):
        if not seen:
            seen.append([p.detach().clone() for p in method.net.parameters()])
        step(method, opt, loss)
        seen.append([p.detach().clone() for p in method.net.parameters()])

    monkeypatch.setattr(T, "optimizer_step", recording)
    method = Ours(tiny(preset("no_tactile"), ema=0.5, lr=1e-2).replace(steps=4))
    T.fit_model(method, demos[:2], [demos[2]], progress=False)
    ema = seen[0]
    for s, weights in enumerate(seen[1:], start=1):
        w = 1.0 - min(0.5, (1 + s) / (10 + s))
        ema = [e + w * (p - e) for e, p in zip(ema, weights, strict=True)]
    kept = [p.detach() for p in method.net.parameters()]
    for k, e in zip(kept, ema, strict=True):
        torch.testing.assert_close(k, e)
    assert not all(torch.allclose(k, last) for k, last in zip(kept, seen[-1], strict=True))


@pytest.mark.parametrize("fraction", [0.3, 1.0])
def test_candidate_draws_keep_the_best_scoring_one_exactly_as_trained_alone(demos, monkeypatch, fraction):
    torch.set_num_threads(1)
    from services.policy import train as T

    cfg = tiny(preset("multimodal"), ema=0.9, steps=6, candidates=2, candidate_fraction=fraction, seed=3)
    picked = []
    score = T.selection_score

    def rigged(method, scored):  # the second draw scores better at the pick, whatever its rollouts say
        res = score(method, scored)
        if len(picked) < 2:
            picked.append(method.cfg.candidate)
            res["score"] = 1.0 - method.cfg.candidate
        return res

    monkeypatch.setattr(T, "selection_score", rigged)
    method = Ours(cfg)
    T.fit_model(method, demos[:2], None, progress=False)
    assert picked == [0, 1] and method.cfg.candidate == 1 and method.cfg.init_seed == 7
    assert [c["candidate"] for c in method.candidate_scores] == [0, 1]
    assert len(method.losses) == cfg.steps
    alone = Ours(cfg.replace(candidates=1, seed=7))  # the same draw trained on its own
    T.fit_model(alone, demos[:2], None, progress=False)
    np.testing.assert_allclose(method.losses, alone.losses, rtol=1e-6)
    for a, b in zip(method.net.state_dict().values(), alone.net.state_dict().values(), strict=True):
        torch.testing.assert_close(a, b)
    np.testing.assert_array_equal(method.reservoir.W_R, alone.reservoir.W_R)


def test_turn_averaging_makes_the_step_equivariant_to_quarter_turns(trained, demos):
    # four turns over the whole circle: the set of turned inputs is closed under a quarter turn,
    # so the averaged output turns with the scene exactly; one net alone is not equivariant
    state = trained.initial_state(demos[2])
    state["mask"][[3, 30, 45]] = False  # masked points take the folded pass's correction path
    quarter = dict(state, pos=D.rotate_z(state["pos"], np.pi / 2), vel=D.rotate_z(state["vel"], np.pi / 2))
    saved = trained.cfg
    try:
        for turns, equal in ((1, False), (4, True)):
            trained.cfg = saved.replace(turns=turns, turn_spread=np.pi * 3 / 4)  # -135, -45, 45, 135 deg
            for fold in (True, False):
                trained.fold_inference = fold
                a, b = trained.network_outputs(state), trained.network_outputs(quarter)
                turned = D.rotate_z(a["vel"].reshape(-1, 3), np.pi / 2).reshape(-1)
                assert np.allclose(b["vel"], turned, rtol=1e-4, atol=1e-5) == equal
                assert np.allclose(b["mask"], a["mask"], rtol=1e-4, atol=1e-5) == equal
    finally:
        trained.cfg, trained.fold_inference = saved, True


def test_turned_copies_go_through_the_folded_pass_as_one_batch(trained, demos):
    state = trained.initial_state(demos[2])
    state["mask"][[3, 30, 45]] = False
    saved = trained.cfg
    try:
        trained.cfg = saved.replace(turns=3, turn_spread=0.5)
        trained.fold_inference = True
        batched = trained.network_outputs(state)
        trained.fold_inference = False
        looped = trained.network_outputs(state)
        for key in batched:
            np.testing.assert_allclose(batched[key], looped[key], rtol=1e-4, atol=1e-5)
    finally:
        trained.cfg, trained.fold_inference = saved, True


def test_rigid_fit_recovers_a_rigid_motion_and_stays_finite_on_a_line():
    from services.policy.consistency import rigid_fit

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


ROLL_CASES = {k: SWITCHES[k] for k in ("multimodal", "no_tactile", "single_state", "no_masks", "no_dynamics")} | {
    "no_follow": {"follow_unobserved": False}, "per_point_dynamics": {"body_dynamics": False}}


@pytest.mark.parametrize("case", sorted(ROLL_CASES))
def test_compiled_rollout_equals_the_step_loop(demos, case):
    """P4's compiled horizon (compiled.py) is the same rollout as Ours.step after Ours.step:
    hidden points at the start and whatever the untrained net masks later, memory, tactile."""
    torch.set_num_threads(1)
    method = Ours(tiny(preset("multimodal", **ROLL_CASES[case])))
    method.setup(demos[:2])
    method.net.eval()
    with torch.no_grad():  # the dynamics head at full size: an untrained J_D barely moves the objects
        method.net.head.weight.mul_(3.0)
    assert method.compiled() is not None
    rng = np.random.default_rng(0)
    state = method.initial_state(demos[2])
    P = len(state["pos"])
    mask = np.ones(P, bool)
    mask[[3, 21, 22, 44]] = False
    state = dict(state, mask=mask, tactile=rng.uniform(0, 30, (2, 6)), tmask=rng.random((2, 6)) < 0.5)
    for dt in (None, 0.05):  # the sample period, and the optimizer's knots
        solver = method.solver(dt)
        # 12 steps: float32 rounding grows through an untrained net's memory gains (20-40x) over longer ones
        fast = method.roll(state, 12, solver)
        method.compile_inference = False
        slow = method.roll(state, 12, solver)
        method.compile_inference = True
        assert np.abs(fast[0][-1] - state["pos"]).max() > 1e-3  # it moved
        for name, a, b in zip(("positions", "tactile", "memory"), fast, slow, strict=True):
            # float32 products summed in another order; tactile is in kPa (20x the net's output)
            np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5 * np.abs(b).max(initial=0.1),
                                       err_msg=f"{name}, dt {dt}")


@pytest.mark.parametrize("case", ["multimodal", "no_masks", "single_state"])
def test_one_step_through_the_compiled_loop_is_the_python_step(demos, case):
    """P4: ``Ours.step`` runs through the compiled loop where it can; every field of the next
    state (positions, velocities, mask, tactile, memory, time) is the Python step's."""
    torch.set_num_threads(1)
    method = Ours(tiny(preset("multimodal", **ROLL_CASES[case])))
    method.setup(demos[:2])
    method.net.eval()
    state = method.initial_state(demos[2])
    mask = np.ones(len(state["pos"]), bool)
    mask[[3, 44]] = False
    state = dict(state, mask=mask, tactile=np.full((2, 6), 12.0), tmask=np.ones((2, 6), bool))
    solver = method.solver()
    fast = [state]
    for _ in range(3):
        fast.append(method.step(fast[-1], solver))
    assert method.compiled() is not None
    method.compile_inference = False
    slow = [state]
    for _ in range(3):
        slow.append(method.step(slow[-1], solver))
    method.compile_inference = True
    for a, b in zip(fast[1:], slow[1:], strict=True):
        assert a.keys() == b.keys()
        for key in b:
            np.testing.assert_allclose(np.asarray(a[key], float), np.asarray(b[key], float), rtol=1e-4,
                                       atol=1e-5 * np.abs(np.asarray(b[key], float)).max(initial=1.0), err_msg=key)
    assert (fast[1]["mask"] != mask).any() or case == "no_masks"  # the net's own mask came through


def test_compiled_rollout_refuses_nan_and_compiles_once(demos):
    from services.policy import compiled as C

    method = Ours(tiny(preset("multimodal")))
    method.setup(demos[:2])
    method.net.eval()
    C.warm()
    state = method.initial_state(demos[2])
    method.roll(state, 3)
    assert len(C._rollout.signatures) == 1  # warm() compiled what the real call runs
    with torch.no_grad():
        method.net.head.bias[0] = float("nan")
    with pytest.raises(PolicyError, match="NaN"):
        method.roll(state, 3)
    assert Ours(tiny(preset("multimodal"), turns=3)).cfg.turns == 3
    turned = Ours(tiny(preset("multimodal"), turns=3))
    turned.setup(demos[:2])
    turned.net.eval()
    assert turned.compiled() is None  # turned copies keep the step loop
