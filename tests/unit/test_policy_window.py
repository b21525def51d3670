"""The time-window observation of Table 7.1 row (4) (services/policy/window.py): block means by hand,
padding at an episode start, training windows against the rollout's, and the net reading them."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from evaluation.evaluate import EvaluationError, evaluate, make_method
from learning.ours import Ours
from learning.presets import PRESETS, preset
from services.policy.runner import PolicyRunner, SceneObs
from services.policy.window import (
    WindowError,
    block_means,
    check_blocks,
    history_length,
    pad_history,
    push_history,
    step_windows,
)
from tests.unit.policy_demos import synthetic_demo

THESIS = (8, 4, 2, 1, 1)


def ramp(n: int, points: int = 2) -> np.ndarray:
    """(n, points, 3): sample t of point p is (t, 10 p, -t)."""
    t = np.arange(n, dtype=float)[:, None]
    p = np.arange(points, dtype=float)[None]
    return np.stack(np.broadcast_arrays(t + 0 * p, 10 * p + 0 * t, -t + 0 * p), axis=-1)


def test_block_means_are_the_hand_computed_means_of_8_4_2_1():
    history = ramp(15)  # samples 0..14 before the current one (15)
    means, seen = block_means(history, np.ones((15, 2), bool), THESIS)
    assert history_length(THESIS) == 15 and means.shape == (4, 2, 3)
    np.testing.assert_allclose(means[:, 0, 0], [3.5, 9.5, 12.5, 14.0])  # mean(0..7), mean(8..11), (12,13), 14
    np.testing.assert_allclose(means[:, 1, 1], 10.0)
    np.testing.assert_allclose(means[:, 0, 2], [-3.5, -9.5, -12.5, -14.0])
    assert seen.all()


def test_a_block_observes_a_point_only_if_every_sample_of_it_did():
    mask = np.ones((15, 2), bool)
    mask[9, 1] = False  # in the second block (samples 8..11) of point 1
    _, seen = block_means(ramp(15), mask, THESIS)
    np.testing.assert_array_equal(seen, [[True, True], [True, False], [True, True], [True, True]])


def test_an_episode_start_is_padded_with_its_first_sample_and_the_history_moves_on():
    first = np.array([[1.0, 2.0, 3.0]])
    history = pad_history(first, THESIS)
    assert history.shape == (15, 1, 3) and (history == first).all()
    means, _ = block_means(history, np.ones((15, 1), bool), THESIS)
    np.testing.assert_allclose(means, np.broadcast_to(first, (4, 1, 3)))
    later = push_history(history, first + 16.0)
    np.testing.assert_allclose(later[-1], first + 16.0)
    np.testing.assert_allclose(later[:-1], history[1:])
    means, _ = block_means(later, np.ones((15, 1), bool), THESIS)
    np.testing.assert_allclose(means[:, 0, 0], [1.0, 1.0, 1.0, 17.0])  # only the newest block saw it


def test_training_windows_equal_the_rollouts_history_and_never_cross_episodes():
    """step_windows over two concatenated episodes is block_means of the history a rollout carries
    (padded at each episode's start with that episode's first sample)."""
    a, b = ramp(20), ramp(7) + 100.0
    pos = np.concatenate([a, b])
    mask = np.ones(pos.shape[:2], bool)
    mask[3, 0] = False
    step = np.concatenate([np.arange(20), np.arange(7)])
    means, seen = step_windows(pos, mask, step, THESIS)
    for episode, offset in ((a, 0), (b, 20)):
        history = pad_history(episode[0], THESIS)
        hmask = pad_history(mask[offset], THESIS)
        for t in range(len(episode)):
            want, want_seen = block_means(history, hmask, THESIS)
            np.testing.assert_allclose(means[offset + t], want, err_msg=f"sample {offset + t}")
            np.testing.assert_array_equal(seen[offset + t], want_seen)
            history = push_history(history, episode[t])
            hmask = push_history(hmask, mask[offset + t])
    assert means[20:, ..., 0].min() >= 100.0  # the second episode never reads the first (x >= 100)
    assert not seen[4:12, :, 0].all()  # sample 3's hidden point 0 is in the windows after it


@pytest.mark.parametrize("blocks", [(8, 4, 2), (1,), (2, 0, 1), (2.5, 1)])
def test_windows_that_do_not_end_at_the_current_sample_are_refused(blocks):
    with pytest.raises(WindowError):
        check_blocks(blocks)


def test_row_4_is_our_network_with_the_window_and_row_3s_training():
    method = make_method("time_window")
    assert isinstance(method, Ours)
    assert method.recipe.model.window == THESIS
    assert method.recipe.train == PRESETS["single_state"].train  # same budget and recipe as row (3)
    assert method.recipe.train.steps == 8000


def test_an_unknown_row_fails_loudly(tmp_path):
    with pytest.raises(KeyError, match="unknown baseline"):
        make_method("state_mlp")
    with pytest.raises(EvaluationError, match="unknown method"):
        evaluate(methods=["state_mlp"], out_dir=tmp_path, quick=True, progress=False)


@pytest.fixture(scope="module")
def window_method():
    torch.set_num_threads(1)
    demos = [synthetic_demo(i) for i in (1, 2, 3)]
    method = Ours(preset("time_window", hidden=(32, 32), steps=3, batch=16, eval_every=10 ** 6))
    method.fit(demos[:2], progress=False)
    return method, demos


def test_the_net_reads_the_window_and_its_training_batches_carry_it(window_method):
    method, demos = window_method
    net = method.net
    assert net.n_window == 4 * net.layout.P * 3
    data = method.setup(demos[:2])
    assert data.window.shape == (len(data), 4, net.layout.P, 3)
    batch = method.make_batch(data, np.random.default_rng(0), 8)
    # the window turns with its sample about gravity: the height (z) is untouched, distances kept
    raw = data.window[batch["index"]]
    np.testing.assert_allclose(batch["window"][..., 2], raw[..., 2])
    np.testing.assert_allclose(np.linalg.norm(batch["window"][..., :2], axis=-1), np.linalg.norm(raw[..., :2], axis=-1))
    state = method.policy.initial_state(demos[2])
    moved = dict(state, window_pos=state["window_pos"] + 0.02)
    assert np.abs(method.policy.step(moved)["pos"] - method.policy.step(state)["pos"]).max() > 1e-6
    with pytest.raises(ValueError, match="window history"):
        method.policy.roll({k: v for k, v in state.items() if not k.startswith("window")}, 2)


def test_the_runner_carries_the_window_history_from_step_to_step(window_method):
    method, demos = window_method
    runner = PolicyRunner(method.policy)
    demo = demos[2]
    states = []
    for t in range(3):
        runner.step(SceneObs(demo.hands[t], demo.hand_mask[t].astype(bool), demo.objects[t],
                             demo.object_mask[t].astype(bool), None, None))
        states.append(runner.state["pos"].copy())
    history = runner.predicted["window_pos"]  # what the next step starts from
    assert history.shape == (15, method.net.layout.P, 3)
    np.testing.assert_array_equal(history[:13], np.repeat(states[:1], 13, axis=0))  # padded with the first scene
    np.testing.assert_array_equal(history[13:], states[1:])  # then each stepped sample
