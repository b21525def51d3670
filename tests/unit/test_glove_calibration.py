"""`xm glove calibrate` on a recording made of the simulated glove and reference forces."""

from __future__ import annotations

import json

import numpy as np

from services.glove import cli
from services.glove.sensor_model import GloveSensorModel
from services.recorder.writer import McapRecorder
from shared import msgs


def test_calibrate_recovers_a_calibration_with_high_correlation(tmp_path):
    model = GloveSensorModel(0)
    rec = McapRecorder(tmp_path / "cal.mcap")
    rng = np.random.default_rng(0)
    for i in range(600):
        t = i * 0.01
        forces = np.zeros((2, 6))
        if i % 100 > 30:  # presses of varying strength, with unloaded stretches between them
            forces[0, :5] = rng.uniform(0, 8) * np.array([1, 1, 0.5, 0.3, 0.2])
        z = model.impedance(forces[0], t)
        rec.write("xm/glove/left/raw", "xm_msgs/msg/TactileRaw", msgs.serialize(msgs.make(
            "xm_msgs/msg/TactileRaw", header=msgs.header(t), hand="left", rows=16, cols=16,
            real=z.real.ravel().astype(np.float32), imag=z.imag.ravel().astype(np.float32), sequence=i)))
        rec.write("xm/world/sim/truth", "xm_msgs/msg/GroundTruth", msgs.serialize(msgs.make(
            "xm_msgs/msg/GroundTruth", header=msgs.header(t), hand_names=["left", "right"],
            hand_keypoints=np.zeros(126, np.float32), hand_visible=np.ones(42, np.uint8), object_names=[],
            object_keypoints=np.zeros(0, np.float32), object_visible=np.zeros(0, np.uint8), body_names=[],
            body_poses=np.zeros(0, np.float32), contact_forces=forces.ravel().astype(np.float32))))
    rec.close()
    out = tmp_path / "glove-left.json"
    assert cli.main(["calibrate", str(tmp_path / "cal.mcap"), "--hand", "left", "-o", str(out)]) == 0
    report = json.loads(out.with_suffix(".report.json").read_text())
    assert report["rational"]["correlation"] > 0.99
    assert report["rational"]["relative_nonlinearity"] > 0.0
    assert out.with_suffix(".png").exists()
    assert cli.main(["calibrate", str(tmp_path / "missing.mcap")]) == 2
