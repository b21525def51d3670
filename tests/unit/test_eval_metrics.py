from __future__ import annotations

import numpy as np
import pytest

from learning.metrics import aligned, closest_point_distance, trajectory_scores
from tests.unit.policy_demos import synthetic_demo


def test_symmetric_closest_point_by_hand():
    # one keypoint; prediction visits x=0 and x=2, reference x=0,1,5
    a = np.array([[0.0, 0, 0], [2.0, 0, 0]])[:, None]
    b = np.array([[0.0, 0, 0], [1.0, 0, 0], [5.0, 0, 0]])[:, None]
    # a->b: 0, 1 -> 0.5 ; b->a: 0, 1, 3 -> 4/3 ; symmetric (0.5 + 4/3) / 2
    assert closest_point_distance(a, b) == pytest.approx((0.5 + 4 / 3) / 2)
    assert closest_point_distance(b, a) == pytest.approx((0.5 + 4 / 3) / 2)


def test_masking_counts_only_observed_reference_samples():
    a = np.array([[0.0, 0, 0], [2.0, 0, 0]])[:, None]
    b = np.array([[0.0, 0, 0], [1.0, 0, 0], [5.0, 0, 0]])[:, None]
    mask = np.array([[1], [1], [0]])  # x=5 unobserved
    # a->b (observed 0,1): 0, 1 -> 0.5 ; b->a (observed only): 0, 1 -> 0.5
    assert closest_point_distance(a, b, mask) == pytest.approx(0.5)


def test_predicted_samples_count_only_where_the_reference_saw_the_point():
    # reference: seen at x=0 (t 0-4), carried to x=1 while occluded (t 5-9), seen at x=1 (t 10-14)
    x = np.r_[np.zeros(5), np.linspace(0.2, 1.0, 5), np.ones(5)]
    b = np.stack([x, 0 * x, 0 * x], -1)[:, None]
    seen = np.r_[np.ones(5), np.zeros(5), np.ones(5)].astype(bool)[:, None]
    detour = b.copy()
    detour[5:10, 0, 2] = 0.5  # a different route while nobody sees the point, same start and end
    still = np.zeros_like(b)
    assert closest_point_distance(detour, b, seen, seen) == 0.0
    # kept still: its seen-time samples sit on the seen start; the seen end (x=1) is 1 away from it
    assert closest_point_distance(still, b, seen, seen) == pytest.approx(0.25)
    # compared without the prediction's mask, the detour's occluded samples would count against it
    assert closest_point_distance(detour, b, seen) > 0.0


def test_aligned_masks_follow_the_prediction_clock():
    m = np.array([[1, 0], [0, 1], [1, 1]], bool)
    assert aligned(m, 2).tolist() == [[True, False], [False, True]]
    assert aligned(m, 5)[3:].tolist() == [[True, True], [True, True]]  # held at the reference's last step


def test_keypoints_are_matched_only_to_themselves_and_averaged():
    # keypoint 0 identical, keypoint 1 offset by 0.3 in z; a swap of identities must not help
    a = np.zeros((3, 2, 3))
    a[:, 1, 0] = 1.0
    b = a.copy()
    b[:, 1, 2] += 0.3
    assert closest_point_distance(a, b) == pytest.approx(0.15)
    swapped = a[:, ::-1]
    assert closest_point_distance(swapped, a) == pytest.approx(1.0)


def test_never_observed_keypoint_is_left_out_and_all_unobserved_is_nan():
    a = np.zeros((2, 2, 3))
    b = np.zeros((2, 2, 3))
    b[:, 1, 0] = 7.0  # far, but never observed
    assert closest_point_distance(a, b, np.array([[1, 0], [1, 0]])) == 0.0
    assert np.isnan(closest_point_distance(a, b, np.zeros((2, 2))))


def test_shape_errors():
    with pytest.raises(ValueError):
        closest_point_distance(np.zeros((3, 2, 3)), np.zeros((3, 4, 3)))
    with pytest.raises(ValueError):
        closest_point_distance(np.zeros((3, 2, 3)), np.zeros((3, 2, 3)), np.ones((2, 2)))
    with pytest.raises(ValueError, match="mask_a"):
        closest_point_distance(np.zeros((3, 2, 3)), np.zeros((3, 2, 3)), None, np.ones((2, 2)))


def test_trajectory_scores_hand_and_object_separately():
    demo = synthetic_demo(1)
    exact = trajectory_scores(demo.hands, demo.objects, demo)
    assert exact["hand"] == pytest.approx(0.0, abs=1e-6) and exact["object"] == pytest.approx(0.0, abs=1e-6)
    # masked: a predicted sample counts only where the reference saw the point, so a copy scores 0
    assert exact["object_masked"] == pytest.approx(0.0, abs=1e-6)
    assert exact["hand_masked"] == pytest.approx(0.0, abs=1e-6)
    moved = trajectory_scores(demo.hands + np.float32(0.01), demo.objects, demo)
    # a constant 1 cm shift along all three axes: at most sqrt(3) cm, objects untouched
    assert 0.005 < moved["hand"] <= 0.0174
    assert moved["object"] == pytest.approx(0.0, abs=1e-6)
    assert moved["hand_masked"] > 0.005
