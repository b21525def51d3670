from __future__ import annotations

import numpy as np

from services.glove.crosstalk import compensate, naive, readings


def contacts(rng: np.random.Generator) -> np.ndarray:
    """Resting cells ~1 MOhm, a few pressed spots down to ~1 kOhm."""
    G = np.full((16, 16), 1e-6) * rng.uniform(0.8, 1.2, (16, 16))
    for _ in range(rng.integers(1, 6)):
        r, c = rng.integers(0, 15, 2)
        G[r:r + 2, c:c + 2] = rng.uniform(1e-4, 1e-3)
    return G


def test_compensation_recovers_random_multi_contact_patterns():
    rng = np.random.default_rng(0)
    g_ref = 1e-3  # 1 kOhm reference resistors
    worst_naive, worst = 0.0, 0.0
    for _ in range(50):
        G = contacts(rng)
        v = readings(G, g_ref)
        worst_naive = max(worst_naive, np.max(np.abs(naive(v, g_ref) - G) / G))
        worst = max(worst, np.max(np.abs(compensate(v, g_ref) - G) / G))
    assert worst_naive > 0.3  # crosstalk is real: ghosting of 30 % or more without compensation
    assert worst < 1e-6  # compensated: the truth within 1 ppm
