"""Hand identity before triangulation: swapped or doubled hand channels, views that lost a hand,
and object detections far from where the object is tracked (services/recon/hand_identity.py)."""

from __future__ import annotations

import numpy as np

from services.recon.hand_identity import absent_hands, assign_hands, gate_tracked, outside_windows, ray_distances
from services.recon.pipeline import Reconstructor
from services.recon.triangulation import project
from shared.geometry import look_at, projection

K = np.array([[250.0, 0, 128], [0, 250.0, 96], [0, 0, 1]])
EYES = [np.array([0.9 * np.cos(a), 0.9 * np.sin(a), 0.7]) for a in np.linspace(0.3, 2 * np.pi + 0.3, 6,
                                                                                 endpoint=False)]
P = np.stack([projection(K, look_at(e, np.array([0.0, 0.0, 0.1]))) for e in EYES])


def two_hands(rng: np.random.Generator, apart: float = 0.35) -> np.ndarray:
    """(42, 3): a left hand and a right hand ``apart`` metres from each other, each 21 keypoints
    within 6 cm of its centre."""
    left = rng.uniform(-0.06, 0.06, (21, 3)) + [0.0, -apart / 2, 0.15]
    right = rng.uniform(-0.06, 0.06, (21, 3)) + [0.0, apart / 2, 0.15]
    return np.concatenate([left, right])


def test_ray_distance_is_zero_for_the_point_a_pixel_was_projected_from():
    rng = np.random.default_rng(0)
    pts = rng.uniform(-0.2, 0.2, (5, 3)) + [0, 0, 0.1]
    uv, _ = project(P, pts)
    d = ray_distances(P, uv, pts)
    assert d.shape == (len(P), 5, 5)
    assert np.allclose(np.diagonal(d, axis1=1, axis2=2), 0.0, atol=1e-9)
    assert (d[:, 0, 1:] > 1e-3).all()


def test_swapped_and_doubled_channels_go_back_to_the_hand_they_show():
    rng = np.random.default_rng(1)
    hands = two_hands(rng)
    uv, _ = project(P, hands)
    conf = np.full(uv.shape[:2], 0.8)
    # The two views where the hands lie farthest apart in the image (where a view's rays through
    # one hand pass near the other, the detections cannot tell and keep their channels).
    gap = [np.linalg.norm(uv[c, :21, None] - uv[c, None, 21:], axis=-1).min() for c in range(len(P))]
    c0, c1 = np.argsort(gap)[-2:]
    bad = uv.copy()
    bad[c0] = np.concatenate([uv[c0, 21:], uv[c0, :21]])  # left and right channels swapped
    bad[c1, 21:] = uv[c1, :21]  # the right channels on the left hand too
    tracked = [hands[:21], hands[21:]]
    a = assign_hands(P, bad, conf, tracked, 21, threshold=0.1)
    assert np.allclose(a.uv[c0], uv[c0])  # the swap is undone
    assert a.swapped == 42
    assert np.allclose(a.uv[c1, :21], uv[c1, :21])  # the left hand keeps its own detections
    assert (a.confidence[c1, 21:] == 0).all()  # and the right hand is not seen there
    assert a.dropped == 21
    rest = [c for c in range(len(P)) if c not in (c0, c1)]
    assert np.allclose(a.uv[rest], uv[rest]) and (a.confidence[rest] == 0.8).all()


def test_without_a_track_the_channels_are_trusted_and_a_lost_hand_is_found_again():
    rng = np.random.default_rng(2)
    hands = two_hands(rng)
    uv, _ = project(P, hands)
    conf = np.full(uv.shape[:2], 0.8)
    untouched = assign_hands(P, uv, conf, [None, None], 21, threshold=0.1)
    assert np.array_equal(untouched.confidence, conf) and untouched.swapped == untouched.dropped == 0
    # The right hand untracked: its own detections count, unless they lie on the tracked left hand.
    gap = [np.linalg.norm(uv[c, :21, None] - uv[c, None, 21:], axis=-1).min() for c in range(len(P))]
    order = np.argsort(gap)[::-1]
    bad = uv.copy()
    bad[order[0], 21:] = uv[order[0], :21]
    a = assign_hands(P, bad, conf, [hands[:21], None], 21, threshold=0.1)
    assert (a.confidence[order[0], 21:] == 0).all()
    # Where the hands lie apart in the image the untracked hand keeps its own detections (where a
    # ray through it also passes the tracked hand, the detection cannot tell and is left out).
    assert (a.confidence[order[1:4], 21:] == 0.8).all()
    assert np.allclose(a.uv[:, :21], uv[:, :21])


def test_a_view_with_weak_detections_of_a_hand_does_not_show_it():
    conf = np.full((3, 42), 0.7)
    conf[1, :21] = 0.2  # view 1 lost the left hand
    conf[2, 21:30] = 0.1  # view 2: a few weak right keypoints (occluded fingers) still show the hand
    absent = absent_hands(conf, hands=2, keypoints=21, min_median=0.5)
    assert absent.tolist() == [[False, False], [True, False], [False, False]]


def test_object_detections_far_from_the_tracked_object_are_dropped():
    rng = np.random.default_rng(3)
    pts = rng.uniform(-0.1, 0.1, (4, 3)) + [0.1, 0.1, 0.0]
    uv, _ = project(P, pts)
    uv[2, 1] += [40.0, 0.0]  # view 2 sees keypoint 1 elsewhere
    conf = np.full(uv.shape[:2], 0.9)
    out, dropped = gate_tracked(P, uv, conf, pts, np.array([True, True, True, False]))
    assert dropped == 1 and out[2, 1] == 0.0
    assert (np.delete(out.ravel(), 2 * 4 + 1) == 0.9).all()
    unknown, none = gate_tracked(P, uv, conf, pts, np.zeros(4, bool))
    assert none == 0 and np.array_equal(unknown, conf)


def test_reconstruction_keeps_each_hand_when_views_swap_its_channels():
    """A hand moving through frame sets while two views swap the channels and one view puts both
    hands' channels on the left hand: once both hands are tracked every keypoint stays with its
    hand (without identity the swaps, agreed on by two views, pull the keypoints across)."""
    rng = np.random.default_rng(4)
    base = two_hands(rng)
    errors = {True: [], False: []}
    for identity in (True, False):
        rec = Reconstructor("assembly", object_names=[], fit_hands=False, identity=identity)
        for f in range(8):
            hands = base + [0.01 * f, 0.0, 0.0]
            uv, _ = project(P, hands)
            conf = np.full(uv.shape[:2], 0.8)
            if f >= 2:
                for c in (0, 3):
                    uv[c] = np.concatenate([uv[c, 21:], uv[c, :21]])
                uv[4, 21:] = uv[4, :21]
            r = rec.step(P, uv, conf)
            seen = r.hand_mask.ravel().astype(bool)
            if f >= 2:
                errors[identity].append(np.linalg.norm(r.hands.reshape(-1, 3) - hands, axis=1)[seen].max())
        if identity:
            assert rec.hand_swaps > 0
    assert max(errors[True]) < 1e-3
    assert max(errors[False]) > 0.1


def test_tracked_points_outside_a_views_window_are_marked_unseen_there():
    pts = np.array([[0.0, 0.0, 0.1], [0.3, 0.3, 0.0]])
    uv, _ = project(P, pts)
    full = np.tile([0.0, 0.0, 256.0, 192.0], (len(P), 1))
    tight = full.copy()
    tight[0] = [uv[0, 0, 0] - 10, uv[0, 0, 1] - 10, 20, 20]  # view 0 reads a window around point 0 only
    out = outside_windows(P, pts, np.array([True, True]), tight)
    inside_full = ~outside_windows(P, pts, np.array([True, True]), full)
    assert not out[0, 0] and out[0, 1] == inside_full[0, 1]
    assert (out[1:] == ~inside_full[1:]).all()
    assert not outside_windows(P, pts, np.array([False, False]), tight).any()
