"""Resistive matrix crosstalk (thesis 4.3, 4.3.1): forward model and compensation against truth."""

from __future__ import annotations

import numpy as np

from services.glove.crosstalk import compensate, direct, naive, network_readings, readings


def contacts(rng: np.random.Generator) -> np.ndarray:
    """Resting cells ~1 MOhm, one to six pressed spots (2x2 or 3x1) down to ~1 kOhm."""
    G = np.full((16, 16), 1e-6) * rng.uniform(0.8, 1.2, (16, 16))
    for _ in range(rng.integers(1, 7)):
        r, c = rng.integers(0, 14, 2)
        h, w = (2, 2) if rng.random() < 0.5 else (3, 1)
        G[r:r + h, c:c + w] = rng.uniform(1e-4, 1e-3)
    return G


def test_forward_model_matches_the_nodal_solve_of_the_network():
    rng = np.random.default_rng(3)
    for _ in range(5):
        G = contacts(rng)
        np.testing.assert_allclose(readings(G, 1e-3), network_readings(G, 1e-3), rtol=1e-12)


def test_a_press_ghosts_into_its_column_without_compensation():
    G = np.full((16, 16), 1e-6)
    G[3, 5] = 1e-3
    v = readings(G, 1e-3)
    ghost = naive(v, 1e-3)
    # Other cells of column 5 read half of what they are; other columns only feel their resting cells.
    assert np.all(ghost[np.arange(16) != 3, 5] < 0.7 * 1e-6)
    np.testing.assert_allclose(ghost[:, 6], G[:, 6], rtol=0.03)


def test_compensation_recovers_random_multi_contact_patterns():
    """Tolerance: 1e-6 relative per cell on noiseless readings (naive divider: >= 30 % off)."""
    rng = np.random.default_rng(0)
    g_ref = 1e-3  # 1 kOhm reference resistors
    worst_naive, worst, worst_direct = 0.0, 0.0, 0.0
    for _ in range(100):
        G = contacts(rng)
        v = readings(G, g_ref)
        worst_naive = max(worst_naive, np.max(np.abs(naive(v, g_ref) - G) / G))
        worst = max(worst, np.max(np.abs(compensate(v, g_ref) - G) / G))
        worst_direct = max(worst_direct, np.max(np.abs(direct(v, g_ref) - G) / G))
    assert worst_naive > 0.3
    assert worst < 1e-6 and worst_direct < 1e-6


def test_compensation_with_measurement_noise_stays_close():
    """12-bit ADC-like noise on the readings: compensated cells within 2 % of the pressed truth."""
    rng = np.random.default_rng(1)
    G = contacts(rng)
    v = readings(G, 1e-3) + rng.normal(0, 1 / 4096, (16, 16))
    est = compensate(v, 1e-3)
    pressed = G > 1e-5
    assert np.max(np.abs(est[pressed] - G[pressed]) / G[pressed]) < 0.02
