"""The running state of PolicyRunner is the neural simulation's: each step starts from the last
step's prediction (touch, masks, memory, window) with the observation merged in."""

from __future__ import annotations

import numpy as np
import pytest

from services.policy.model import Policy
from services.policy.runner import PolicyRunner, SceneObs
from shared.demo import KEYPOINTS_PER_HAND, Demo
from tests.unit.policy_demos import synthetic_demo
from tests.unit.test_policy_inference import untrained

STEPS = 12
GLOVE = np.array([True, False])  # predicted touch fed back on the left hand, as a left glove would read


@pytest.fixture(scope="module")
def demos() -> list[Demo]:
    return [synthetic_demo(1, grasp="left"), synthetic_demo(2, grasp="right"), synthetic_demo(3, grasp="left")]


@pytest.fixture(scope="module")
def net(demos) -> Policy:
    return untrained(demos, window=(2, 1, 1))  # touch, memory, masks and a time window


def scene(d: Demo, t: int = 0) -> SceneObs:
    """A scene with no touch reading (a robot, or no glove)."""
    return SceneObs(d.hands[t].astype(float), d.hand_mask[t].astype(bool), d.objects[t].astype(float),
                    d.object_mask[t].astype(bool))


def reference(net: Policy, d: Demo) -> tuple[np.ndarray, np.ndarray]:
    """The neural simulation from the same start: positions and touch of STEPS steps."""
    start = PolicyRunner(net, glove=GLOVE).observe(scene(d))
    pos, tact, _ = net.roll(start, STEPS)
    assert tact[:, 0].max() > 1.0  # the check below means something only if touch is fed back
    return pos, tact


def test_steps_without_new_scenes_are_the_neural_simulation(net, demos):
    d = demos[2]
    pos, tact = reference(net, d)
    runner = PolicyRunner(net, glove=GLOVE)
    got = [runner.step(scene(d))] + [runner.step(None) for _ in range(STEPS - 1)]
    np.testing.assert_allclose(np.array(got), pos, atol=1e-9)
    np.testing.assert_allclose(runner.efforts, tact[-1], atol=1e-9)


def test_in_the_loop_touch_is_the_open_loop_touch(net, demos):
    """Scenes of the predicted points without touch (the robot loop): the net is given its own
    predicted touch, so it predicts what the neural simulation predicts."""
    d = demos[2]
    pos, tact = reference(net, d)
    runner = PolicyRunner(net, glove=GLOVE)
    obs, efforts = scene(d), []
    for _ in range(STEPS):
        nxt = runner.step(obs)
        efforts.append(runner.efforts.copy())
        n = 2 * KEYPOINTS_PER_HAND
        obs = SceneObs(nxt[:n].reshape(2, KEYPOINTS_PER_HAND, 3), runner.predicted["mask"][:n].reshape(2, -1),
                       nxt[n:], runner.predicted["mask"][n:])
    np.testing.assert_allclose(np.array(efforts), tact, atol=1e-9)
    np.testing.assert_allclose(runner.predicted["tactile"], tact[-1], atol=1e-9)


def test_an_occluded_point_keeps_its_prediction_and_a_glove_reading_replaces_touch(net, demos):
    d = demos[2]
    runner = PolicyRunner(net, glove=GLOVE)
    predicted = runner.step(scene(d))
    predicted_touch = runner.efforts.copy()
    later = scene(d, 1)
    later.hands[1, 5] = np.nan
    later.tactile, later.tactile_mask = np.full((2, 6), 7.0), np.array([[False] * 6, [True] * 6])
    state = runner.observe(later)
    np.testing.assert_array_equal(state["pos"][KEYPOINTS_PER_HAND + 5], predicted[KEYPOINTS_PER_HAND + 5])
    assert not state["mask"][KEYPOINTS_PER_HAND + 5]
    np.testing.assert_array_equal(state["tactile"][0], predicted_touch[0])  # no reading: the prediction
    np.testing.assert_array_equal(state["tactile"][1], 7.0)  # the glove's reading
    np.testing.assert_array_equal(state["tmask"], later.tactile_mask)


def test_without_a_glove_the_net_is_given_no_touch(net, demos):
    runner = PolicyRunner(net)
    runner.step(scene(demos[2]))
    assert not runner.state["tmask"].any()
