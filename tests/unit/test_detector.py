"""The learned keypoint detector's pure parts: sub-pixel peaks, the COCO label format, the mapping
from network pixels back to full-image pixels through the letterbox and the readout window, the
runtime class's input checks, and a short training run whose loss falls."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from perception.augment import NO_AUGMENT, letterbox_matrix, sample
from perception.labels import Frame, keypoint_names, read_coco, write_coco
from perception.train import train
from services.recon.detector import CameraModel
from services.recon.learned_detector import (
    TRAIN_HINT,
    LearnedDetector,
    UNet,
    View,
    WeightsMissingError,
    image_to_net,
    net_to_full,
    peaks,
    to_input,
)


@pytest.fixture(autouse=True)
def denormals_restored():
    """The detector flushes denormals to zero for speed (process-wide in a recon service); the tests
    that follow in this process (hypothesis refuses to run in that mode) get normal floats back."""
    yield
    torch.set_flush_denormal(False)


def gaussians(centres: np.ndarray, size: tuple[int, int], sigma: float) -> np.ndarray:
    ys, xs = np.mgrid[:size[1], :size[0]]
    return np.exp(-((xs[None] - centres[:, 0, None, None]) ** 2 + (ys[None] - centres[:, 1, None, None]) ** 2)
                  / (2 * sigma**2))


def test_peaks_recover_subpixel_gaussian_centres():
    rng = np.random.default_rng(0)
    centres = rng.uniform([1.5, 1.5], [30.5, 22.5], (200, 2))
    for sigma in (1.0, 1.5, 2.5):
        uv, conf = peaks(gaussians(centres, (32, 24), sigma) * 0.7)
        assert np.abs(uv - centres).max() < 1e-3
        assert np.allclose(conf, 0.7, atol=1e-3)


def test_peaks_handle_noise_borders_and_empty_maps():
    rng = np.random.default_rng(1)
    centres = rng.uniform([2, 2], [29, 21], (100, 2))
    noisy = gaussians(centres, (32, 24), 1.5) + rng.normal(0, 0.02, (100, 24, 32))
    uv, _ = peaks(noisy)
    assert np.median(np.linalg.norm(uv - centres, axis=1)) < 0.15
    edge = gaussians(np.array([[0.0, 5.0], [31.0, 23.0]]), (32, 24), 1.5)
    uv, _ = peaks(edge)
    assert np.allclose(uv, [[0.0, 5.0], [31.0, 23.0]], atol=1e-6)
    uv, conf = peaks(np.zeros((2, 3, 8, 8)))  # leading axes kept, no NaN
    assert uv.shape == (2, 3, 2) and conf.shape == (2, 3) and np.isfinite(uv).all() and (conf == 0).all()


def test_letterbox_and_window_map_back_to_full_image_pixels():
    rng = np.random.default_rng(2)
    roi = (98, 52, 66, 74)
    uv_window = rng.uniform(0, 60, (10, 2))
    for s in (0.5, 1.0, 96 / 66):
        back = net_to_full(image_to_net(uv_window, s), s, roi)
        assert np.allclose(back, uv_window + [98, 52])
    assert np.allclose(net_to_full(image_to_net(uv_window, 0.75), 0.75, None), uv_window)
    # the training-time affine and the inference-time letterbox agree
    M = letterbox_matrix(66, 74, (96, 72))
    s = min(96 / 66, 72 / 74)
    assert np.allclose(uv_window @ M[:, :2].T + M[:, 2], image_to_net(uv_window, s))


def test_to_input_places_a_pixel_where_image_to_net_says():
    img = np.zeros((40, 80, 3), np.uint8)
    img[19:22, 49:52] = 255  # a bright 3x3 square centred on (50, 20)
    batch, scales = to_input([img], (96, 72))
    assert batch.shape == (1, 3, 72, 96) and scales[0] == pytest.approx(1.2)
    ys, xs = np.nonzero(batch[0, 0] > 0.5)
    expect = image_to_net(np.array([50.0, 20.0]), scales[0])
    assert abs(xs.mean() - expect[0]) < 0.6 and abs(ys.mean() - expect[1]) < 0.6
    assert batch[0, :, 49:, :].max() == 0.0  # padding below the letterboxed content


def frames_of(task: str, n: int, rng: np.random.Generator) -> list[Frame]:
    names = keypoint_names(task)
    out = []
    for i in range(n):
        vis = rng.integers(0, 3, len(names)).astype(np.uint8)
        uv = np.round(rng.uniform(0, 60, (len(names), 2)), 3)
        out.append(Frame(f"images/{i:04d}_cam{i % 7}.png", f"cam{i % 7}", (10 * i, 4, 64, 62), (256, 192), uv, vis,
                         {"seed": 3, "demo": 1, "time": 0.5 * i}))
    return out


def test_coco_labels_round_trip(tmp_path):
    rng = np.random.default_rng(3)
    frames = frames_of("assembly", 5, rng)
    frames[0].visibility[:] = 0  # an image without any labelled keypoint stays in the set
    write_coco(tmp_path / "labels.json", "assembly", frames, "test")
    doc = json.loads((tmp_path / "labels.json").read_text())
    assert [c["name"] for c in doc["categories"]] == ["left_hand", "right_hand", "board", "camera"]
    assert all(len(a["keypoints"]) == 3 * len(next(c for c in doc["categories"] if c["id"] == a["category_id"])
                                              ["keypoints"]) for a in doc["annotations"])
    task, back = read_coco(tmp_path / "labels.json")
    assert task == "assembly" and len(back) == len(frames)
    for a, b in zip(frames, back, strict=True):
        assert (a.file_name, a.camera, a.roi, a.full_size, a.extra) == (b.file_name, b.camera, b.roi, b.full_size,
                                                                         b.extra)
        assert np.array_equal(a.visibility, b.visibility)
        lab = a.visibility > 0
        assert np.allclose(a.uv[lab], b.uv[lab], atol=1e-3)


def test_coco_labels_with_other_keypoints_are_refused(tmp_path):
    write_coco(tmp_path / "labels.json", "assembly", frames_of("assembly", 1, np.random.default_rng(4)), "test")
    doc = json.loads((tmp_path / "labels.json").read_text())
    doc["categories"][2]["keypoints"] = ["c0", "c1"]
    (tmp_path / "labels.json").write_text(json.dumps(doc))
    with pytest.raises(ValueError, match="board"):
        read_coco(tmp_path / "labels.json")


def weights_folder(tmp_path, size=(32, 24)):
    names = keypoint_names("assembly")
    torch.save(UNet(len(names)).state_dict(), tmp_path / "weights.pt")
    (tmp_path / "meta.json").write_text(json.dumps({"task": "assembly", "keypoints": names, "input_size": list(size)}))
    return tmp_path


def test_detector_reports_full_image_pixels_of_the_heatmap_peaks(tmp_path):
    det = LearnedDetector(weights_folder(tmp_path), runtime="torch")
    n = len(det.names)
    rois = [(100, 40, 64, 48), (0, 0, 256, 192)]
    truth = np.array([[[110.0 + k % 40, 50.0 + k % 30] for k in range(n)], [[20.0 + 4 * k, 100.0] for k in range(n)]])
    views = [View(f"cam{i}", CameraModel(np.zeros((3, 4)), 256, 192, roi), np.zeros((roi[3], roi[2], 3), np.uint8))
             for i, roi in enumerate(rois)]
    scales = [min(32 / r[2], 24 / r[3]) for r in rois]

    def fake_heatmaps(batch):  # Gaussians where the true keypoints land in the network's input
        return np.stack([gaussians(image_to_net(truth[i] - rois[i][:2], scales[i]), (32, 24), 1.5)
                         for i in range(len(rois))]).astype(np.float32)

    det.heatmaps = fake_heatmaps
    uv, conf = det.detect(views)
    assert uv.shape == (2, n, 2) and conf.shape == (2, n)
    inside = image_to_net(truth[1], scales[1])[:, 0] < 31  # keypoints beyond the map's edge are clipped to it
    assert np.allclose(uv[0], truth[0], atol=1e-3)
    assert np.allclose(uv[1][inside], truth[1][inside], atol=1e-3)


def test_detector_rejects_wrong_images_and_says_how_to_train(tmp_path):
    with pytest.raises(WeightsMissingError, match="xm detector label && xm detector train"):
        LearnedDetector(tmp_path / "none")
    assert "xm detector train" in TRAIN_HINT
    det = LearnedDetector(weights_folder(tmp_path), runtime="torch")
    cam = CameraModel(np.zeros((3, 4)), 256, 192, (10, 10, 64, 48))
    with pytest.raises(ValueError, match="cam3: image is 60x48 but its window"):
        det.detect([View("cam3", cam, np.zeros((48, 60, 3), np.uint8))])
    with pytest.raises(ValueError, match="RGB uint8"):
        det.detect([View("cam3", cam, np.zeros((48, 64), np.uint8))])
    uv, conf = det.detect([View("cam3", cam, np.zeros((48, 64, 3), np.uint8))])
    assert uv.shape == (1, len(det.names), 2) and np.isfinite(uv).all() and ((conf >= 0) & (conf <= 1)).all()


def test_training_sample_targets_follow_the_augmentation():
    rng = np.random.default_rng(5)
    img = np.zeros((60, 80, 3), np.uint8)
    uv = np.array([[20.0, 30.0], [70.0, 10.0], [0.0, 0.0]])
    vis = np.array([2, 1, 0], np.uint8)
    x, y = sample(img, uv, vis, (40, 32), 1.5, NO_AUGMENT, rng)
    assert x.shape == (3, 32, 40) and y.shape == (3, 32, 40)
    got, conf = peaks(y[:2])
    assert np.allclose(got, image_to_net(uv[:2], 0.5), atol=1e-3) and np.allclose(conf, 1.0, atol=0.1)
    assert y[2].max() == 0.0  # unlabelled: no target


def test_a_short_training_run_lowers_the_loss():
    rng = np.random.default_rng(6)
    names = keypoint_names("assembly")
    frames, images = [], []
    for i in range(4):  # bright discs at the labelled keypoints of a few synthetic images
        img = np.full((48, 64, 3), 40, np.uint8)
        uv = rng.uniform(4, 44, (len(names), 2))
        vis = np.zeros(len(names), np.uint8)
        vis[:3] = 2
        for u, v in uv[:3]:
            img[int(v) - 1:int(v) + 2, int(u) - 1:int(u) + 2] = 255
        frames.append(Frame(f"{i}.png", "cam0", (0, 0, 64, 48), (64, 48), uv, vis))
        images.append(img)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # deterministic sums; restored for the tests after this one
    try:
        _, losses, _ = train(frames, images, len(names), (32, 24), iters=40, minutes=5, batch_size=4, lr=3e-3,
                             aug=NO_AUGMENT, progress=False)
    finally:
        torch.set_num_threads(threads)
    assert len(losses) == 40
    assert np.mean(losses[-5:]) < 0.5 * np.mean(losses[:5])
