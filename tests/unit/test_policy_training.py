"""Learning the chapter-7 policy: augmentation, the reservoir, denoising samples, losses, the
recipe switches, the training loop and its checkpoints."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import torch

from learning import dataset as D
from learning import train as T
from learning.ours import Ours, train
from learning.presets import PRESETS, Recipe, config_changes, preset
from learning.reservoir import Reservoir
from services.policy.model import Policy
from shared.demo import Demo
from tests.unit.policy_demos import synthetic_demo

K = 4


@pytest.fixture(scope="module")
def demos() -> list[Demo]:
    return [synthetic_demo(1, grasp="left"), synthetic_demo(2, grasp="right"), synthetic_demo(3, grasp="left")]


def tiny(recipe: Recipe, **kw) -> Recipe:
    return recipe.replace(**{"hidden": (32, 32), "steps": 3, "batch": 16, "eval_every": 10 ** 6} | kw)


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
    np.testing.assert_allclose(b["target_vel"], b["next_vel"] - R * method.correction_gain(data.dt))


def test_goal_bodies_name_the_unmoved_object_a_pinch_heads_for_within_a_second():
    T, dt = 200, 0.02
    pos = np.zeros((T, 42 + 2, 3))
    pos[:, 42] = [0.3, 0.0, 0.0]  # object 0 stays put
    pos[:, 43] = [0.0, 0.3, 0.0]  # object 1 ...
    pos[150:, 43, 2] = 0.1  # ... is lifted at 3 s
    reach = np.clip(np.linspace(0, 2, T), 0, 1)[:, None] * [0.0, 0.3, 0.0]  # the left pinch reaches object 1 at 2 s
    pos[:, 4] = pos[:, 8] = reach
    pos[:, 21:42] = [-1.0, -1.0, 0.0]  # the right hand stays far from both
    goal = D.goal_bodies(pos, np.ones(pos.shape[:2], bool), np.array([0, 1]), dt)
    assert (goal[:, 1] == -1).all()
    assert goal[0, 0] == -1 and (goal[60:150, 0] == 1).all()  # within 1 s of the reach, until object 1 moves
    assert (goal[150:, 0] == -1).all()  # a moved (carried) object is no goal


def test_goal_relative_denoising_moves_a_hands_target_with_the_object_it_heads_for(demos):
    method = Ours(tiny(preset("multimodal"), goal_relative=True, lag_noise=0.0))
    data = method.setup(demos[:2])
    b = method.make_batch(data, np.random.default_rng(0), 64)
    R, gain, body = b["pos"] - b["clean_pos"], method.correction_gain(data.dt), method.body
    shift = b["target_vel"] - (b["next_vel"] - R * gain)
    for k in range(64):
        for h in range(2):
            g = b["goal"][k, h]
            want = R[k, body == 2 + g].mean(0) * gain if g >= 0 else np.zeros(3)
            np.testing.assert_allclose(shift[k, body == h], np.broadcast_to(want, (21, 3)), atol=1e-9)
        np.testing.assert_allclose(shift[k, body >= 2], 0.0, atol=1e-9)
    assert (b["goal"] >= 0).any(), "the synthetic demonstrations reach for an object"


def test_the_correction_gain_is_f_n_capped_at_one_step():
    assert Ours(preset("no_tactile")).correction_gain(0.02) == 8.0
    assert Ours(preset("no_tactile", noise_gain=80.0)).correction_gain(0.02) == 50.0


def test_the_seed_draws_weights_reservoir_and_samples(demos):
    nets = {}
    for seed in (0, 0, 1):
        method = Ours(tiny(preset("multimodal"), seed=seed))
        method.setup(demos[:2])
        nets.setdefault(seed, []).append(method)
    (a, again), (other,) = nets[0], nets[1]
    np.testing.assert_array_equal(a.reservoir.W_R, again.reservoir.W_R)
    assert not np.allclose(other.reservoir.W_R, a.reservoir.W_R)
    for p, q, r in zip(a.net.trunk.parameters(), again.net.trunk.parameters(), other.net.trunk.parameters(),
                       strict=True):
        torch.testing.assert_close(p, q)
        assert not torch.allclose(p, r)


def test_config_changes_are_typed_like_their_fields_and_bad_ones_named():
    got = config_changes(["reservoir_periods=0.25,8", "hidden=64,32", "mirror=false", "lr=3e-4", "steps=10",
                          "w_dyn=1.5"])
    assert got == {"reservoir_periods": (0.25, 8.0), "hidden": (64, 32), "mirror": False, "lr": 3e-4, "steps": 10,
                   "w_dyn": 1.5}
    r = preset("multimodal", **got)
    assert (r.model.hidden, r.train.mirror, r.inference.w_dyn) == ((64, 32), False, 1.5)
    for bad, says in (("colour=red", "'colour=red'"), ("steps", "'steps'"), ("steps=ten", "not a int"),
                      ("mirror=maybe", "not a bool"), ("name=x", "'name=x'"),
                      ("velocity_input=true", "velocity_input")):
        with pytest.raises(ValueError, match=says):
            config_changes([bad])
    with pytest.raises(ValueError, match="unknown recipe field"):
        preset("multimodal", candidates=2)
    # the window's default is empty: its values are integers, and an empty value is no window
    assert config_changes(["window=8,4,2,1,1"]) == {"window": (8, 4, 2, 1, 1)}
    assert config_changes(["window="]) == {"window": ()}
    with pytest.raises(ValueError, match="not a tuple"):
        config_changes(["window=8,x"])


def test_body_dynamics_trains_j_where_the_holding_hand_hides_its_pinch():
    """The thumb of the carrying hand is hidden while it carries: without the stand-in velocity no
    sample where the object moves reaches the J_D loss."""
    hidden = []
    for d in (synthetic_demo(1, grasp="left"), synthetic_demo(3, grasp="left")):
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


SWITCHES = {
    "no_tactile": {"tactile": False},
    "single_state": {"tactile": False, "memory": False},
    "no_denoise": {"denoise": False},
    "no_masks": {"masks": False},
    "no_pairs": {"pair_outputs": False},
    "no_dynamics": {"dynamics": False},
    "per_point_dynamics": {"body_dynamics": False},
    "no_rotate_no_mirror": {"rotate": False, "mirror": False},
    "no_lag_noise": {"lag_noise": 0.0},
    "no_follow": {"follow_unobserved": False},
    "no_memory_prior": {"w_memory_prior": 0.0},
    "time_window": {"window": (8, 4, 2, 1, 1)},
}


@pytest.fixture(scope="module")
def reference_rollout(demos):
    torch.set_num_threads(1)
    method = Ours(tiny(preset("multimodal")))
    method.fit(demos[:2], progress=False)
    return method.rollout(demos[2], 12)


@pytest.mark.parametrize("switch", sorted(SWITCHES))
def test_every_switch_trains_and_changes_the_rollout(demos, reference_rollout, switch):
    """Each switch of the recipe trains, rolls out finite, and changes what the tiny net does
    (same seed: without the switch the rollout is the reference's, bit for bit)."""
    torch.set_num_threads(1)
    method = Ours(tiny(preset("multimodal"), **SWITCHES[switch]))
    method.fit(demos[:2], progress=False)
    assert len(method.losses) == 3 and np.isfinite(method.losses).all()
    hands, objects = method.rollout(demos[2], 12)
    assert hands.shape == (12, 2, 21, 3) and objects.shape == (12, K, 3)
    assert np.isfinite(hands).all() and np.isfinite(objects).all()
    np.testing.assert_allclose(hands[0], demos[2].hands[0], atol=1e-6)
    ref_hands, ref_objects = reference_rollout
    assert max(np.abs(hands - ref_hands).max(), np.abs(objects - ref_objects).max()) > 1e-7


def test_the_reference_rollout_is_reproduced_bit_for_bit(demos, reference_rollout):
    torch.set_num_threads(1)
    method = Ours(tiny(preset("multimodal")))
    method.fit(demos[:2], progress=False)
    hands, objects = method.rollout(demos[2], 12)
    np.testing.assert_array_equal(hands, reference_rollout[0])
    np.testing.assert_array_equal(objects, reference_rollout[1])


def test_training_reduces_the_loss(demos):
    torch.set_num_threads(1)
    method = Ours(preset("single_state", hidden=(64, 64), steps=150, batch=64, eval_every=10 ** 6, lr=3e-3))
    method.fit(demos[:2], progress=False)
    assert np.mean(method.losses[-20:]) < 0.6 * np.mean(method.losses[:20])


def test_the_folded_copy_follows_a_fused_optimizer_step(demos):
    # the fused step does not bump version counters: the training step must drop the folded copy,
    # or every selection rollout after the first scores stale weights
    method = Ours(tiny(preset("no_tactile"), lr=1e-2))
    data = method.setup(demos[:2])
    before = method.rollout(demos[2], 5)[0]
    opt = T.make_optimizer(method.net, method.recipe.train.lr)
    loss, _ = method.loss(method.make_batch(data, np.random.default_rng(0), 16))
    T.optimizer_step(method, opt, loss)
    after = method.rollout(demos[2], 5)[0]
    assert not np.allclose(after, before)
    fresh = Policy.from_state(method.policy.state())  # folded anew from the same weights
    np.testing.assert_array_equal(fresh.rollout(demos[2], 5)[0], after)


def test_ema_weights_are_what_is_scored_and_kept(demos, monkeypatch):
    seen = []  # the weights before the first step, then after each
    step = T.optimizer_step

    def recording(method, opt, loss):
        if not seen:
            seen.append([p.detach().clone() for p in method.net.parameters()])
        step(method, opt, loss)
        seen.append([p.detach().clone() for p in method.net.parameters()])

    monkeypatch.setattr(T, "optimizer_step", recording)
    method = Ours(tiny(preset("no_tactile"), ema=0.5, lr=1e-2, steps=4))
    T.fit_model(method, demos[:2], [demos[2]], progress=False)
    ema = seen[0]
    for s, weights in enumerate(seen[1:], start=1):
        w = 1.0 - min(0.5, (1 + s) / (10 + s))
        ema = [e + w * (p - e) for e, p in zip(ema, weights, strict=True)]
    kept = [p.detach() for p in method.net.parameters()]
    for k, e in zip(kept, ema, strict=True):
        torch.testing.assert_close(k, e)
    assert not all(torch.allclose(k, last) for k, last in zip(kept, seen[-1], strict=True))


def test_checkpoint_round_trip_weights_only_with_the_training_demonstrations(demos, tmp_path):
    torch.set_num_threads(1)
    res = train(tiny(preset("multimodal")), demos[:2], demos[2:], tmp_path / "run", progress=False)
    assert res.checkpoint.exists() and (tmp_path / "run" / "loss.png").exists()
    again = Policy.from_state(torch.load(res.checkpoint, weights_only=True))
    assert (again.cfg, again.inference, again.name) == (res.method.policy.cfg, res.method.policy.inference,
                                                         "multimodal")
    assert again.record["train"]["steps"] == 3  # training's settings, for the record
    h1, o1 = res.method.rollout(demos[2], 10)
    h2, o2 = again.rollout(demos[2], 10)
    np.testing.assert_array_equal(h2, h1)
    np.testing.assert_array_equal(o2, o1)
    saved = sorted((tmp_path / "run" / "demos").glob("*.npz"))  # what the node's naive fallback replays
    assert len(saved) == 2 and np.array_equal(Demo.load(saved[1]).hands, demos[1].hands)
    assert json.loads((tmp_path / "run" / "config.json").read_text())["model"]["hidden"] == [32, 32]


def test_presets_differ_only_in_their_modalities():
    mm, nt, ss, tw = (PRESETS[k] for k in ("multimodal", "no_tactile", "single_state", "time_window"))
    assert mm.model.tactile and not nt.model.tactile and not ss.model.memory
    assert tw.model == replace(ss.model, window=(8, 4, 2, 1, 1))  # row (4): row (3) fed the thesis's window
    assert mm.train == nt.train == ss.train == tw.train and mm.inference == nt.inference == ss.inference == tw.inference
