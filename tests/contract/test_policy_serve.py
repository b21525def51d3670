"""policy @cmd/serve (the dashboard's model list): another checkpoint loads while the current method
keeps planning, then serves; a path that is no checkpoint is refused or leaves the current method
serving, with the reason."""

from __future__ import annotations

import time

from learning.ours import train
from learning.presets import preset
from services.world.teacher import generate_demo
from shared import msgs
from tests.conftest import ServiceProcess, query_json, wait_for, wait_until, write_deployment
from tests.contract.test_pipeline_services import _scene_msg, collect

POLICY = "xm/policy/main"


def test_serve_switches_to_a_trained_checkpoint_and_refuses_bad_ones(router, tmp_path):
    endpoint, session = router
    demos = [generate_demo("assembly", s, index=i) for i, s in enumerate((11, 12))]
    model = tmp_path / "model"
    train(preset("no_tactile", steps=20, hidden=(64, 64), batch=32, eval_every=10_000), demos, None, model,
          progress=False)
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a checkpoint")
    dep = write_deployment(tmp_path / "d.toml", endpoint, {"policy": {"main": {
        "method": "learned", "checkpoint": str(tmp_path / "missing.pt"), "rate_hz": 5.0}}})
    svc = ServiceProcess("policy", dep, "main", tmp_path / "policy.log")
    plans, _sub = collect(session, f"{POLICY}/plan", "xm_msgs/msg/Plan")

    def serve(payload: dict) -> dict:
        return query_json(session, f"{POLICY}/@cmd/serve", payload, timeout=5.0)[0]

    k = 0

    def scene_sent() -> None:
        nonlocal k
        now = time.time()
        session.put("xm/world/sim/session", msgs.serialize(msgs.make(
            "xm_msgs/msg/Session", header=msgs.header(now), task="assembly", demo=0, phase="approach",
            tactile_hand="left", seed_layout="{}")))
        session.put("xm/recon/main/scene", _scene_msg(demos[0], k, now))
        k += 1

    try:
        assert wait_for(lambda: query_json(session, f"{POLICY}/@health"), 60), svc.output()
        state = serve({})
        assert state["ok"] and state["checkpoint"] is None and state["method"] in ("naive", "hold")
        missing = serve({"checkpoint": str(tmp_path / "nowhere.pt")})
        assert missing["ok"] is False and "is not a file" in missing["error"]
        assert serve({"checkpoint": str(junk)})["loading"] == str(junk)
        failed = wait_until(lambda: (s := serve({}))["problem"] and s, 60, lambda: f"the junk refused: {svc.output()}")
        assert "junk.pt unusable" in failed["problem"] and failed["checkpoint"] is None
        # a trained checkpoint: loaded, then its network plans
        assert serve({"checkpoint": str(model / "policy.pt")})["ok"]
        wait_until(lambda: query_json(session, f"{POLICY}/@health")[0]["checkpoint"] == str(model / "policy.pt"), 120,
                   lambda: f"the checkpoint served: {svc.output()}")

        def learned_plans() -> bool:
            scene_sent()
            return any(p.policy == "learned:no_tactile" for p in plans)

        wait_until(learned_plans, 30, lambda: f"plans of the served network: {svc.output()}", period=0.1)
        health = query_json(session, f"{POLICY}/@health")[0]
        assert health["status"] == "ok" and health["method"] == "learned:no_tactile" and health["loading"] is None
    finally:
        svc.stop()
