"""recon on windowed frames: the simulated detector sees only what the readout window shows and
reports full-image pixels (services/recon/detector.py)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from services.recon.detector import CameraModel, SimulatedDetector, readout_window
from shared.geometry import look_at, projection


def test_points_outside_the_window_are_not_seen_and_pixels_stay_full_image():
    K = np.array([[280.0, 0, 160], [0, 280.0, 120], [0, 0, 1]])
    P = projection(K, look_at(np.array([0.3, 0.0, 0.8]), np.zeros(3)))
    pts = np.array([[0.0, 0.0, 0.0], [0.2, 0.2, 0.0]])
    full = CameraModel(P, 320, 240)
    window = CameraModel(P, 320, 240, roi=(120, 80, 80, 80))  # around the image centre only
    det = SimulatedDetector(pixel_noise=0.0, dropout=0.0)
    uv_full, seen_full = det.detect([full], pts)
    uv_win, seen_win = det.detect([window], pts)
    assert seen_full[0].tolist() == [True, True]
    assert seen_win[0].tolist() == [True, False]
    np.testing.assert_allclose(uv_win[0, 0], uv_full[0, 0])  # full-image pixels, not window pixels
    np.testing.assert_allclose(uv_win[0, 0], [160, 120], atol=1e-6)


def test_readout_window_of_camera_info_all_zero_means_full_image():
    info = SimpleNamespace(width=640, height=480, roi=SimpleNamespace(x_offset=0, y_offset=0, width=0, height=0))
    assert readout_window(info) == (0, 0, 640, 480)
    info.roi = SimpleNamespace(x_offset=100, y_offset=60, width=200, height=120)
    assert readout_window(info) == (100, 60, 200, 120)
