"""bench/recon.py updates its own keys of .bench/recon.json and keeps the rest."""

from __future__ import annotations

import json
import sys

import numpy as np

from bench._recon_images import by_hand_distance, hand_distance
from bench.recon import main, merged


def test_merged_replaces_measured_keys_and_keeps_the_others():
    kept = {"images": {"learned_live": {"a": 1, "b": 2}, "aniposelib_note": "x"}, "other_bench": {"k": 1}, "rows": [1]}
    new = {"images": {"learned_live": {"a": 5}}, "rows": [2], "live": {}}
    out = merged(kept, new)
    assert out["images"] == {"learned_live": {"a": 5, "b": 2}, "aniposelib_note": "x"}
    assert out["other_bench"] == {"k": 1} and out["rows"] == [2] and out["live"] == {}
    assert kept["images"]["learned_live"] == {"a": 1, "b": 2}  # the input is left alone


def test_a_run_keeps_what_other_benches_added(tmp_path, monkeypatch):
    path = tmp_path / "recon.json"
    path.write_text(json.dumps({"images": {"learned_live": {"hand_mean_error_mm": 12.0}, "live_objects_note": "n"},
                                "live": {"seconds": 60}, "object_stage_every_view_every_frame_set": {"p6": 1}}))
    monkeypatch.setattr(sys, "argv", ["recon.py", "--out", str(path), "--image-sessions", "0", "--live", "0",
                                      "--no-projected"])
    main()
    out = json.loads(path.read_text())
    assert out["images"] == {"learned_live": {"hand_mean_error_mm": 12.0}, "live_objects_note": "n"}
    assert out["live"] == {"seconds": 60}
    assert out["object_stage_every_view_every_frame_set"] == {"p6": 1}
    assert out["targets"]["object_mean_error_mm"] == 3.0


def test_object_error_split_by_the_nearest_hand():
    objects = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0]])
    hands = np.array([[0.0, 0.02, 0.0], [0.5, 0.5, 0.5]])
    np.testing.assert_allclose(hand_distance(objects, hands), [0.02, np.hypot(0.1, 0.02)])
    assert np.all(np.isinf(hand_distance(objects, hands[:0])))
    err = {"obj": [0.01, 0.03], "obj_near": [0.02, 0.1], "near_all": [0.02, 0.1, 0.1, 0.2]}
    split = by_hand_distance(err)
    assert split["0-3 cm"] == {"reported": 1, "mean_mm": 10.0, "median_mm": 10.0, "share_of_error_sum": 0.25,
                               "coverage": 1.0}
    assert split[">= 6 cm"]["reported"] == 1 and split[">= 6 cm"]["coverage"] == round(1 / 3, 3)
    assert split["3-6 cm"]["reported"] == 0 and split["3-6 cm"]["mean_mm"] is None
