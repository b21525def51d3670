"""Training samples that show no hand: windows cut from full frames away from the hands (first
stage) and hand-sized crops away from every hand (second stage), and a start from a shipped graph."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from perception.augment import NO_AUGMENT
from perception.hand_stage import empty_sample
from perception.labels import Frame
from perception.train import cut_window, export_onnx, graph_weights, window_sampler
from services.recon.learned_detector import UNet

HANDS = 42


def full_frame_with_hands_in_a_corner(rng: np.random.Generator) -> tuple[Frame, np.ndarray]:
    """A 256x192 frame: the hands' keypoints bright in its top-left corner, two object keypoints
    at its bottom right, the rest dark."""
    img = np.full((192, 256, 3), 20, np.uint8)
    uv = np.zeros((HANDS + 2, 2))
    uv[:HANDS] = rng.uniform(5, 45, (HANDS, 2))
    uv[HANDS:] = [[220.0, 160.0], [230.0, 170.0]]
    for u, v in uv[:HANDS]:
        img[int(v) - 2:int(v) + 3, int(u) - 2:int(u) + 3] = 255
    vis = np.full(HANDS + 2, 2, np.uint8)
    return Frame("full.png", "cam0", (0, 0, 256, 192), (256, 192), uv, vis), img


def test_a_cut_window_shows_no_hand_and_keeps_the_labels_inside_it():
    rng = np.random.default_rng(0)
    frame, img = full_frame_with_hands_in_a_corner(rng)
    for _ in range(20):
        cut, uv, vis = cut_window(frame, img, (64, 66), HANDS, rng)
        assert cut.shape == (66, 64, 3)
        assert (vis[:HANDS] > 0).sum() < 4  # almost every place of this frame shows no hand
        inside = np.all((uv >= -0.5) & (uv <= np.array([64, 66]) - 0.5), axis=1)
        assert np.array_equal(vis > 0, inside)  # labelled exactly where the cut holds the keypoint
        x0, y0 = (frame.uv[HANDS] - uv[HANDS]).astype(int)
        assert np.array_equal(cut, img[y0:y0 + 66, x0:x0 + 64])


def test_the_first_stage_sampler_cuts_empty_windows_at_the_labelled_windows_sizes():
    rng = np.random.default_rng(1)
    full, img = full_frame_with_hands_in_a_corner(rng)
    window = Frame("w.png", "cam0", (0, 0, 64, 64), (256, 192), full.uv.copy(), full.visibility)
    sampler = window_sampler([full, window], [img, img[:64, :64].copy()], (64, 48), NO_AUGMENT, 1.0, HANDS)
    hand_peaks = [sampler(rng)[1][:HANDS].max(axis=(1, 2)) for _ in range(30)]
    assert np.mean([(p > 0.5).sum() >= 4 for p in hand_peaks]) < 0.1
    # Without the hand channels named, nothing is cut: windows as labelled, hands and all.
    plain = window_sampler([full, window], [img, img[:64, :64].copy()], (64, 48), NO_AUGMENT, 1.0, 0)
    assert np.mean([(plain(rng)[1][:HANDS].max(axis=(1, 2)) > 0.5).sum() >= 4 for _ in range(30)]) > 0.9


def test_an_empty_hand_crop_is_placed_away_from_the_hands_and_has_no_targets():
    rng = np.random.default_rng(2)
    frame, img = full_frame_with_hands_in_a_corner(rng)
    for _ in range(20):
        x, y = empty_sample(img, frame.uv[:HANDS], np.ones(HANDS, bool), 12.0, 32, NO_AUGMENT, rng)
        assert x.shape == (3, 32, 32) and y.shape == (21, 32, 32)
        assert y.max() == 0.0
        assert x.max() < 0.5  # the bright hand keypoints are not in it


def test_a_graph_gives_back_the_weights_it_was_exported_from(tmp_path):
    pytest.importorskip("onnx")
    torch.manual_seed(0)
    net = UNet(3)
    assert export_onnx(net, (32, 24), tmp_path / "model.onnx")
    state = graph_weights(tmp_path / "model.onnx")
    assert state is not None and set(state) == set(net.state_dict())
    assert all(torch.equal(state[k], v) for k, v in net.state_dict().items())
    assert graph_weights(tmp_path / "missing.onnx") is None
