"""``xm calibrate`` against a running simulated world: the board command, the whole calibration
on rendered frames, and the clear failure when no workcell is up."""

from __future__ import annotations

import json

import numpy as np
import pytest

from calibration.capture import SNAPSHOT_KEY, WORLD_CMD
from services.world import calibration_sequence as calseq
from services.world.render import Snapshot
from shared.calibration import load
from shared.charuco import BoardSpec
from tests.conftest import ServiceProcess, free_endpoint, query_json, run_xm, wait_healthy, write_deployment


def world(tmp_path, endpoint: str):
    dep = write_deployment(tmp_path / "d.toml", endpoint, {"world": {"sim": {"task": "assembly"}}}, clock="sim")
    return dep, ServiceProcess("world", dep, "sim", tmp_path / "world.log")


def board_mocap(session) -> np.ndarray:
    snap = Snapshot.from_json(next(iter(session.get(SNAPSHOT_KEY, timeout=3.0))).ok.payload.to_bytes())
    return snap.mocap_pos[-1]  # the board is the last mocap body


def test_world_places_and_hides_the_board_on_command(router, tmp_path):
    endpoint, session = router
    _, svc = world(tmp_path, endpoint)
    with svc:
        wait_healthy(session, "world", "sim", svc)
        reply = query_json(session, WORLD_CMD, {"index": 0, "count": 10, "seed": 3})[0]
        assert reply["ok"] and reply["board"] == BoardSpec().to_dict()
        expected = calseq.registration_pose(BoardSpec())
        assert np.allclose(reply["world_T_board"], expected)
        assert np.allclose(board_mocap(session), expected[:3, 3])
        later = query_json(session, WORLD_CMD, {"index": 7, "count": 10, "seed": 3})[0]
        assert np.allclose(later["world_T_board"], calseq.sequence(BoardSpec(), 10, 3)[7])
        bad = query_json(session, WORLD_CMD, {"index": 10, "count": 10})[0]
        assert not bad["ok"] and "outside the sequence" in bad["error"]
        assert not query_json(session, WORLD_CMD, {"count": 10})[0]["ok"]
        assert query_json(session, WORLD_CMD, {"hide": True})[0]["hidden"]
        assert board_mocap(session)[2] == calseq.HIDDEN_Z


def test_calibrate_without_a_workcell_says_what_to_start(tmp_path):
    dep = write_deployment(tmp_path / "d.toml", free_endpoint(), {})
    out = run_xm("calibrate", "--deployment", str(dep), "--output", str(tmp_path / "rig.json"), timeout=60)
    assert out.returncode == 2
    assert "xm up" in out.stderr or "is `xm up" in out.stderr, out.stderr


@pytest.mark.slow
def test_xm_calibrate_recovers_the_simulated_cameras(router, tmp_path):
    endpoint, session = router
    dep, svc = world(tmp_path, endpoint)
    with svc:
        wait_healthy(session, "world", "sim", svc)
        out = run_xm("calibrate", "--deployment", str(dep), "--count", "40", "--output", str(tmp_path / "rig.json"),
                     timeout=600)
        assert board_mocap(session)[2] == calseq.HIDDEN_Z  # the board is put away afterwards
    assert out.returncode == 0, out.stdout + out.stderr
    rig = load(tmp_path / "rig.json")
    rig.check_rig({f"cam{i}": (640, 480) for i in range(7)})
    report = json.loads((tmp_path / "rig.report.json").read_text())
    assert (tmp_path / "rig.report.png").stat().st_size > 0
    assert all(c["rms_px"] < 0.3 for c in report["cameras"].values()), report["cameras"]
    assert report["truth_max"]["position_mm"] < 1.5 and report["truth_max"]["rotation_deg"] < 0.1, report["truth_max"]
    assert report["truth_max"]["focal_pct"] < 0.3
