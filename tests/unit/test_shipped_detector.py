"""The keypoint network that ships in models/detector/: recon loads it by default, without
training or downloads, and its channels are the ones recon expects for the deployment's task."""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import pytest

from services.recon.detector import CameraModel
from services.recon.learned_detector import DEFAULT_WEIGHTS_DIR, LearnedDetector, View, load_meta
from services.recon.pipeline import Reconstructor
from services.recon.service import keypoint_names

ROOT = Path(__file__).resolve().parents[2]


def test_the_shipped_network_is_in_the_repository_and_is_the_default():
    assert DEFAULT_WEIGHTS_DIR == ROOT / "models" / "detector"
    assert (DEFAULT_WEIGHTS_DIR / "model.onnx").stat().st_size > 1_000_000
    assert (DEFAULT_WEIGHTS_DIR / "hands.onnx").stat().st_size > 1_000_000  # the second stage, per hand crop
    assert (DEFAULT_WEIGHTS_DIR / "objects.onnx").stat().st_size > 1_000_000  # the object stage, per object crop
    assert not (DEFAULT_WEIGHTS_DIR / "weights.pt").exists(), "the ONNX graph alone ships"
    assert not (DEFAULT_WEIGHTS_DIR / "hands.pt").exists()
    assert not (DEFAULT_WEIGHTS_DIR / "objects.pt").exists()


def test_the_shipped_keypoints_are_the_sim_deployments_task_in_recons_order():
    sim = tomllib.loads((ROOT / "deploy" / "sim.toml").read_text())
    task = sim["services"]["world"]["sim"]["task"]
    meta = load_meta(DEFAULT_WEIGHTS_DIR)
    assert meta["task"] == task
    assert meta["keypoints"] == keypoint_names(Reconstructor(task))


def test_the_shipped_graph_detects_every_keypoint_in_a_frame_set():
    pytest.importorskip("onnxruntime")
    det = LearnedDetector()
    assert det.runtime == "onnx" and det.hand_meta is not None and det.object_meta is not None
    assert det.precision == {"model": "int8", "hands": "int8", "objects": "int8"}, "int8 graphs match the float"
    rng = np.random.default_rng(0)
    views = [View(f"cam{i}", CameraModel(np.zeros((3, 4)), 256, 192, (40, 30, 96, 72)),
                  rng.integers(0, 256, (72, 96, 3), np.uint8)) for i in range(7)]
    uv, conf = det.detect(views)
    assert uv.shape == (7, len(det.names), 2) and conf.shape == (7, len(det.names))
    assert np.isfinite(uv).all() and ((conf >= 0) & (conf <= 1)).all()
    inside = (uv[..., 0] >= 39.5) & (uv[..., 0] <= 136) & (uv[..., 1] >= 29.5) & (uv[..., 1] <= 102)
    assert inside.all(), "peaks map back into each view's window"
