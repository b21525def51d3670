"""policy @cmd/simulate (the dashboard's neural simulation): a checkpoint rolled out from the latest
scene or a given one; predicted hands, objects and tactile per step; bad requests get the reason."""

from __future__ import annotations

import time

import numpy as np

from learning.ours import train
from learning.presets import preset
from services.world.teacher import generate_demo
from tests.conftest import ServiceProcess, query_json, wait_for, wait_until, write_deployment
from tests.contract.test_pipeline_services import _scene_msg

POLICY = "xm/policy/main"


def test_simulate_rolls_a_checkpoint_out_from_a_scene(router, tmp_path):
    endpoint, session = router
    demos = [generate_demo("assembly", s, index=i) for i, s in enumerate((11, 12))]
    train(preset("no_tactile", steps=20, hidden=(64, 64), batch=32, eval_every=10_000), demos, None, tmp_path,
          progress=False)
    dep = write_deployment(tmp_path / "d.toml", endpoint, {"policy": {"main": {
        "method": "naive", "checkpoint": str(tmp_path / "policy.pt"), "rate_hz": 5.0}}})
    svc = ServiceProcess("policy", dep, "main", tmp_path / "policy.log")

    def simulate(payload: dict) -> dict:
        return query_json(session, f"{POLICY}/@cmd/simulate", payload, timeout=30.0)[0]

    ckpt = str(tmp_path / "policy.pt")
    d = demos[1]
    start = {"hands": d.hands[5].ravel().tolist(), "hand_mask": [1] * 42, "objects": d.objects[5].ravel().tolist(),
             "object_mask": [1] * len(d.object_names)}
    try:
        assert wait_for(lambda: query_json(session, f"{POLICY}/@health"), 60), svc.output()
        # naive serves no network, and nothing has been observed yet: each refusal says why
        assert "serves no network" in simulate({})["error"]
        assert "no scene observed yet" in simulate({"checkpoint": ckpt})["error"]
        out = simulate({"checkpoint": ckpt, "start": start, "seconds": 1.0})
        assert out["ok"], out
        steps, k = out["steps"], len(out["object_names"])
        assert steps == round(1.0 / out["dt"]) + 1 and out["object_names"] == d.object_names
        hands = np.reshape(out["hands"], (steps, 2, 21, 3))
        objects = np.reshape(out["objects"], (steps, k, 3))
        assert np.reshape(out["tactile"], (steps, 2, len(out["tactile_regions"]))).shape[0] == steps
        np.testing.assert_allclose(hands[0], d.hands[5], atol=1e-4)  # starts where the scene is
        np.testing.assert_allclose(objects[0], d.objects[5], atol=1e-4)
        assert np.abs(hands[-1] - hands[0]).max() > 0  # and moves on its own predictions
        # from the latest observed scene
        session.put("xm/recon/main/scene", _scene_msg(demos[0], 3, time.time()))
        live = wait_until(lambda: (r := simulate({"checkpoint": ckpt}))["ok"] and r, 20,
                          lambda: f"a rollout from the observed scene: {svc.output()}")
        np.testing.assert_allclose(np.reshape(live["hands"], (-1, 2, 21, 3))[0], demos[0].hands[3], atol=1e-4)
        # bad requests
        assert "not a file" in simulate({"checkpoint": str(tmp_path / "none.pt")})["error"]
        assert "seconds must be" in simulate({"checkpoint": ckpt, "seconds": 0})["error"]
        assert "start scene unusable" in simulate({"checkpoint": ckpt, "start": {"hands": [1, 2]}})["error"]
        wrong = dict(start, objects=[0.0] * 3, object_mask=[1])
        assert "trained with" in simulate({"checkpoint": ckpt, "start": wrong})["error"]
        health = query_json(session, f"{POLICY}/@health")[0]
        assert sum(v for key, v in health["errors"].items() if key.startswith("bad_request")) >= 6
    finally:
        svc.stop()
