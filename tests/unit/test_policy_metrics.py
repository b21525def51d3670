from __future__ import annotations

import numpy as np

from learning.metrics import closest_point_distance


def test_closest_point_distance_by_hand():
    a = np.array([[[0.0, 0, 0]], [[1.0, 0, 0]]])
    b = np.array([[[0.0, 0, 0]], [[0.0, 0, 3.0]]])
    # a->b: 0 and 1 (mean 0.5); b->a: 0 and 3 (mean 1.5); symmetric mean 1.0
    assert closest_point_distance(a, b) == 1.0
    assert closest_point_distance(a, a) == 0.0
    # With the second reference sample masked, only the first counts: a->b 0,1 ; b->a 0
    assert closest_point_distance(a, b, np.array([[1], [0]])) == 0.25


def test_time_shift_is_forgiven_but_a_detour_is_not():
    t = np.linspace(0, 1, 50)
    path = np.stack([t, 0 * t, 0 * t], -1)[:, None]
    assert closest_point_distance(path[5:], path) < 0.02
    detour = path.copy()
    detour[20:30, 0, 2] = 0.1
    assert closest_point_distance(detour, path) > 0.01
