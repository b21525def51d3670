"""Offline smoothing of reconstructed tracks (services/recon/smoothing.py): jitter removed, short
gaps filled, long gaps kept, outliers held off, and the prior idle at the live camera rate."""

from __future__ import annotations

import numpy as np
import pytest

from services.recon.smoothing import HANDS, SmoothParams, segments, smooth_tracks


def motion(t: np.ndarray) -> np.ndarray:
    """A hand-like path (T,1,3): 10 cm swings at about 1 Hz."""
    return np.stack([0.1 * np.sin(2 * np.pi * 0.8 * t), 0.05 * np.cos(2 * np.pi * 1.1 * t), 0.3 + 0.02 * t],
                    axis=-1)[:, None]


def noisy(dt: float, seconds: float = 4.0, noise: float = 0.004, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    t = np.arange(0, seconds, dt)
    truth = motion(t)
    return truth, truth + np.random.default_rng(seed).normal(0, noise / np.sqrt(3), truth.shape)


def err(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.linalg.norm(a - b, axis=-1).mean())


def test_jitter_at_50_hz_is_removed():
    truth, y = noisy(0.02)
    x, mask = smooth_tracks(y, np.ones(y.shape[:2], bool), 0.02, HANDS)
    assert mask.all()
    assert err(x, truth) < 0.5 * err(y, truth)
    step = lambda p: np.diff(p, axis=0)  # noqa: E731
    assert err(step(x), step(truth)) < 0.25 * err(step(y), step(truth))


def test_the_prior_barely_acts_at_5_hz():
    truth, y = noisy(0.2, seconds=20.0)
    x, _ = smooth_tracks(y, np.ones(y.shape[:2], bool), 0.2, HANDS)
    assert err(x, y) < 0.2 * err(y, truth)  # close to the samples: a real motion is not flattened


def test_short_gaps_filled_long_gaps_kept():
    truth, y = noisy(0.02)
    seen = np.ones(y.shape[:2], bool)
    seen[50:58] = False  # 0.16 s: filled
    seen[120:150] = False  # 0.6 s: split, stays masked
    y[~seen] = np.nan
    x, mask = smooth_tracks(y, seen, 0.02, HANDS)
    assert mask[50:58].all() and not mask[120:150].any()
    assert err(x[50:58], truth[50:58]) < 0.01
    assert np.isnan(x[120:150]).all()  # untouched outside the spans


def test_an_outlier_counts_linearly():
    truth, y = noisy(0.02)
    y[100] += 0.10
    x, _ = smooth_tracks(y, np.ones(y.shape[:2], bool), 0.02, HANDS)
    assert err(x[95:106], truth[95:106]) < 0.006


def test_sparse_spans_and_bad_period():
    y = np.zeros((10, 1, 3))
    seen = np.zeros((10, 1), bool)
    seen[[2, 3]] = True
    x, mask = smooth_tracks(y + 1, seen, 0.02, HANDS)
    assert (mask == seen).all() and (x == 1).all()  # two samples: nothing to smooth
    with pytest.raises(ValueError, match="sample period"):
        smooth_tracks(y, seen, 0.0, HANDS)
    assert segments(np.array([0, 1, 1, 0, 0, 0, 1, 0, 1], bool), max_gap=2) == [(1, 3), (6, 9)]


def test_weights_are_physical():
    """The same motion and noise sampled at two rates is smoothed to a similar error per second of
    prior: doubling the rate does not need a new weight."""
    params = SmoothParams(noise_m=0.004, jerk_m_s3=30.0)
    errors = []
    for dt in (0.02, 0.01):
        truth, y = noisy(dt, seed=3)
        x, _ = smooth_tracks(y, np.ones(y.shape[:2], bool), dt, params)
        errors.append(err(x, truth) / err(y, truth))
    assert max(errors) < 0.5
