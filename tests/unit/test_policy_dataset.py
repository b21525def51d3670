"""Recordings -> demonstrations: labels split demos, NaN keypoints masked, gaps and junk reported."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from learning.dataset import DatasetError, demo_arrays, demos_from_mcap, demos_from_messages, step_data


def scene(t: float, nan: bool = False) -> SimpleNamespace:
    hands = np.full(2 * 21 * 3, 0.1 + t, np.float32)
    if nan:
        hands[:3] = np.nan
    return SimpleNamespace(hand_keypoints=hands, hand_mask=np.ones(42, np.uint8), object_names=["a/0", "a/1"],
                           object_keypoints=np.zeros(6, np.float32), object_mask=np.ones(2, np.uint8),
                           tactile=np.zeros(12, np.float32), tactile_mask=np.ones(12, np.uint8))


def session(demo: int) -> SimpleNamespace:
    return SimpleNamespace(demo=demo, task="assembly", phase="approach", tactile_hand="left")


def test_split_by_session_label_masks_nan_and_reports_gaps():
    scenes = [(0.02 * i, scene(0.02 * i, nan=(i == 10))) for i in range(60)]
    scenes += [(5.0 + 0.02 * i, scene(0.0)) for i in range(40)]  # second demonstration
    scenes += [(5.8 + 1.0 + 0.02 * i, scene(0.0)) for i in range(30)]  # after a 1 s gap
    sessions = [(0.0, session(0)), (4.9, session(1))]
    report: list[str] = []
    demos = demos_from_messages(scenes, sessions, report=report, source="rec.mcap")
    assert [d.meta["demo"] for d in demos] == [0, 1]
    assert demos[0].steps == 60 and demos[0].hand_mask[10, 0, 0] == 0 and np.isfinite(demos[0].hands).all()
    assert demos[1].steps == 40
    assert any("demonstration 0" in r and "NaN" in r and "t=0.20" in r for r in report)
    assert any("demonstration 1" in r and "gap" in r for r in report)


def test_a_world_restart_starts_new_demonstrations_even_with_the_same_index():
    # the world restarts at 3 s of recording: its clock, and its demonstration index, start again at 0
    first = [(0.02 * i, scene(0.02 * i)) for i in range(50)]
    second = [(0.02 * i, scene(1.0 + 0.02 * i)) for i in range(40)]
    sessions = [(0.0, session(0)), (0.9, session(0))]
    again = [(0.0, session(0)), (0.5, session(0))]
    report: list[str] = []
    demos = demos_from_messages(first + second, sessions + again, report=report)
    assert [(d.meta["demo"], d.meta["epoch"], d.steps) for d in demos] == [(0, 0, 50), (0, 1, 40)]
    assert demos[1].hands[0, 0, 0, 0] == pytest.approx(1.1)  # the second run's own first scene
    assert not any("gap" in r for r in report)


def test_unlabelled_or_empty_recordings_are_rejected(tmp_path):
    with pytest.raises(DatasetError, match="session"):
        demos_from_messages([(0.0, scene(0.0))], [])
    with pytest.raises(DatasetError, match="no such recording"):
        demos_from_mcap(tmp_path / "missing.mcap")
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap file")
    with pytest.raises(DatasetError, match="junk.mcap"):
        demos_from_mcap(junk)


def test_velocity_masks_follow_occlusion():
    scenes = [(0.02 * i, scene(0.02 * i)) for i in range(30)]
    demo = demos_from_messages(scenes, [(0.0, session(0))])[0]
    demo.hand_mask[7, 0, 2] = 0
    a = demo_arrays(demo)
    assert not a.vmask[7, 2] and not a.vmask[8, 2] and a.vmask[9, 2]
    assert np.all(a.vel[7, 2] == 0)
    data = step_data([a])
    assert len(data) == 29 and np.isclose(data.prob.sum(), 1.0)
