"""Demonstrations as recon reconstructs them (evaluation/reconstructed.py): the windows, the
masks, the cache, and a short clip through the simulated detector against its truth."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from evaluation import reconstructed as R
from evaluation.evaluate import rollouts
from services.world.sim import WorldSim
from services.world.teacher import generate_demo
from shared.demo import Demo

CLIP = 30  # samples of the short clip (0.6 s)


@pytest.fixture(scope="module")
def clip() -> Demo:
    d = generate_demo("assembly", 7, tactile_hand="left", grasp_hand="left", index=0)
    return R.truncated(d, CLIP)


@pytest.fixture(scope="module")
def reconstructed(clip: Demo) -> Demo:
    worker = R.DemoReconstructor("assembly", 0, R.ReconOptions(detector="simulated", lead_in=4))
    try:
        return worker.demo(clip)
    finally:
        worker.close()


def test_options_reject_unknown_detector_and_windows():
    with pytest.raises(R.ReconstructionError, match="detector"):
        R.ReconOptions(detector="oracle")
    with pytest.raises(R.ReconstructionError, match="windows"):
        R.ReconOptions(windows="tiles")


def test_full_frames_when_asked_or_when_no_hand_is_tracked():
    cams, P = R.rig(256, 192)
    assert P.shape == (7, 3, 4)
    for windows in (R.frame_windows(cams, None, 3, R.ReconOptions()),
                    R.frame_windows(cams, np.zeros((5, 3)), 3, R.ReconOptions(windows="full"))):
        assert [tuple(w) for w in windows] == [(0, 0, 256, 192)] * 7


def test_windows_follow_the_tracked_hand():
    cams, _ = R.rig(256, 192)
    hand = np.array([[0.0, 0.0, 0.05]]) + np.random.default_rng(0).normal(0, 0.01, (21, 3))
    windows = R.frame_windows(cams, hand, 3, R.ReconOptions())
    assert any(w.width < 256 or w.height < 192 for w in windows)
    reacquire = R.frame_windows(cams, hand, 10, R.ReconOptions())  # every 10th frame set: full frames
    assert [tuple(w) for w in reacquire] == [(0, 0, 256, 192)] * 7


def test_tracked_hands_are_the_observed_keypoints():
    hands = np.arange(2 * 21 * 3, dtype=float).reshape(2, 21, 3)
    mask = np.zeros((2, 21), np.uint8)
    assert R.tracked_hands(hands, mask) is None
    mask[1, :4] = 1
    np.testing.assert_array_equal(R.tracked_hands(hands, mask), hands[1, :4])


def test_reconstructed_clip_has_the_demonstrations_shapes_and_no_nan(clip, reconstructed):
    r = reconstructed
    assert r.steps == clip.steps
    for name in ("hands", "hand_mask", "objects", "object_mask", "tactile", "tactile_mask"):
        assert getattr(r, name).shape == getattr(clip, name).shape, name
    assert np.isfinite(r.hands).all() and np.isfinite(r.objects).all()
    assert set(np.unique(r.hand_mask)) <= {0, 1} and set(np.unique(r.object_mask)) <= {0, 1}
    assert (r.hands[r.hand_mask == 0] == 0).all() and (r.objects[r.object_mask == 0] == 0).all()
    np.testing.assert_array_equal(r.tactile, clip.tactile)  # the glove is not reconstructed
    assert r.meta["observations"] == "reconstructed:simulated:roi"


def test_reconstructed_clip_is_close_to_truth(clip, reconstructed):
    err = R.reconstruction_error(reconstructed, clip)
    assert err["hand_reported"] > 0.9
    assert err["hand_m"] < 0.008  # recon's live target on hands
    assert err["object_reported"] > 0.3 and err["object_m"] < 0.010
    # not the truth itself: the detector's pixel noise is in it
    assert err["hand_m"] > 1e-4


def test_reconstructed_tracks_are_smoothed(clip, reconstructed):
    worker = R.DemoReconstructor("assembly", 0, R.ReconOptions(detector="simulated", lead_in=4, smooth=False))
    try:
        raw = worker.demo(clip)
    finally:
        worker.close()

    def step_error(r: Demo) -> float:  # frame-to-frame motion against the true motion
        both = (r.hand_mask[1:] & r.hand_mask[:-1]).astype(bool)
        return float(np.linalg.norm(np.diff(r.hands, axis=0) - np.diff(clip.hands, axis=0), axis=-1)[both].mean())

    assert step_error(reconstructed) < 0.5 * step_error(raw)
    assert R.reconstruction_error(reconstructed, clip)["hand_m"] < R.reconstruction_error(raw, clip)["hand_m"]


def test_observed_steps_train_whole_validation_start():
    d = generate_demo("assembly", 3, index=1)
    assert R.observed_steps(replace(d, meta={**d.meta, "split": "train"})) == d.steps
    assert R.observed_steps(replace(d, meta={**d.meta, "split": "validation"})) == 1


def test_cache_is_reused_and_keyed(tmp_path, clip, monkeypatch):
    opts = R.ReconOptions(detector="simulated", lead_in=2)
    demos = [replace(clip, meta={**clip.meta, "split": "train"}),
             replace(clip, meta={**clip.meta, "split": "validation"})]
    first = R.reconstructed_demos(demos, "assembly", 0, opts, tmp_path, progress=False, steps=[5, 1])
    assert [d.steps for d in first] == [5, 1]
    assert [d.meta["split"] for d in first] == ["train", "validation"]
    assert len(list(tmp_path.glob("*/demo_*.npz"))) == 2

    class Refuse:
        def __init__(self, *args, **kwargs):
            raise AssertionError("reconstructed again despite the cache")

    monkeypatch.setattr(R, "DemoReconstructor", Refuse)
    again = R.reconstructed_demos(demos, "assembly", 0, opts, tmp_path, progress=False, steps=[3, 1])
    np.testing.assert_array_equal(again[0].hands, first[0].hands[:3])
    assert R.cache_key(0, opts) != R.cache_key(1, opts)
    assert R.cache_key(0, opts) != R.cache_key(0, replace(opts, windows="full"))
    key = R.cache_key(0, opts)
    monkeypatch.setattr(R, "RECON_SOURCES", (*R.RECON_SOURCES, "tests/unit/test_policy_reconstructed.py"))
    assert R.cache_key(0, opts) != key  # other reconstruction code, another cache


def test_learned_detector_without_weights_says_how_to_train(tmp_path):
    with pytest.raises(R.ReconstructionError, match="xm detector train"):
        R.cache_key(0, R.ReconOptions(detector="learned", weights=str(tmp_path)))


def test_rollouts_start_from_the_observed_start_and_last_as_the_truth():
    seen = []

    class Method:
        name = "probe"

        def rollout(self, start: Demo, steps: int):
            seen.append(start.meta["tag"])
            return np.zeros((steps, 2, 21, 3)), np.zeros((steps, start.objects.shape[1], 3))

    truth = generate_demo("assembly", 5, index=0)
    truth.meta["tag"] = "truth"
    start = R.truncated(replace(truth, meta={**truth.meta, "tag": "observed"}), 1)
    outs = rollouts(Method(), [truth], False, [start])
    assert seen == ["observed"] and outs[0][0].shape[0] == truth.steps


def test_held_objects_fill_masked_points_with_the_last_seen_position(clip):
    mask = np.ones_like(clip.object_mask)
    mask[5:12, 0] = 0
    mask[:3, 1] = 0
    objs = clip.objects.copy()
    objs[mask == 0] = 0.0  # what a reconstructed demonstration carries where it saw nothing
    held = R.held_objects(replace(clip, objects=objs, object_mask=mask), smooth=1)
    assert held.object_mask.all()
    np.testing.assert_allclose(held.objects[5:12, 0], np.repeat(clip.objects[4:5, 0], 7, 0))
    np.testing.assert_allclose(held.objects[:3, 1], np.repeat(clip.objects[3:4, 1], 3, 0))
    np.testing.assert_allclose(held.objects[12:], clip.objects[12:])


def test_cell_observer_sees_the_objects_at_the_camera_rate():
    sim = WorldSim("assembly", seed=0, width=32, height=24)
    sim.start_demo(3)
    sim.set_robot_mode("robot")
    observer = R.CellObserver("assembly", 0, 3, R.ReconOptions(detector="simulated"), period_s=0.1)
    try:
        assert observer.update(sim) and not observer.update(sim)  # one frame set per period
        for _ in range(4):
            observer.frame_set(sim)
        _, truth = sim.object_keypoints()
        seen = observer.mask
        assert seen.sum() >= 5
        assert np.linalg.norm(observer.objects[seen] - truth[seen], axis=1).max() < 0.01
        sim.step(int(round(0.1 / sim.physics_dt)))
        assert observer.update(sim)
    finally:
        observer.close()
