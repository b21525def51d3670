"""bench/glove.py's bookkeeping: per-frame stages lined up by sequence number."""

from __future__ import annotations

import numpy as np

from bench.glove import percentiles, stage_times


def test_stages_line_up_by_sequence_and_skip_frames_outside_the_run():
    due = np.array([10.0, 10.001, 10.002])
    # (sequence, read returned, decoded, published): out of order, plus the warm-up frame (10**6)
    trace = np.array([[2, 10.0025, 10.0026, 10.0027], [0, 10.0004, 10.0005, 10.0006],
                      [10**6, 9.0, 9.0, 9.0], [1, 10.0013, 10.0015, 10.0016]])
    got = {0: 10.0010, 2: 10.0030}  # frame 1 never arrived
    st = stage_times(trace, due, got)
    np.testing.assert_allclose(st["pty"], [0.0005, 0.0004, 0.0003], atol=1e-9)
    np.testing.assert_allclose(st["decode"], [0.0001, 0.0001, 0.0002], atol=1e-9)
    np.testing.assert_allclose(st["deliver"][[0, 1]], [0.0003, 0.0004], atol=1e-9)
    assert np.isnan(st["deliver"][2])
    p = percentiles(st["deliver"])  # undelivered frames are left out, not counted as 0
    assert abs(p["max"] - 0.4) < 1e-6 and abs(p["p50"] - 0.35) < 1e-6
    assert np.isnan(percentiles(np.array([np.nan]))["p99"])
