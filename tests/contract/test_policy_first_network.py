"""policy waiting for its first network (a fresh install, or a checkpoint that does not load): it
holds, replays the demonstrations once the training job has written them, and serves the network
once its checkpoint appears, saying so in @health all along."""

from __future__ import annotations

import time

import pytest

from learning.ours import train
from learning.presets import preset
from learning.train import save_demos
from services.world.teacher import generate_demo
from shared import msgs
from tests.conftest import ServiceProcess, query_json, wait_until, write_deployment
from tests.contract.test_pipeline_services import _scene_msg, collect

POLICY = "xm/policy/main"


@pytest.mark.parametrize("start", ["missing", "unloadable"])
def test_policy_switches_from_fallback_to_the_first_network_when_it_appears(router, tmp_path, start):
    endpoint, session = router
    demos = [generate_demo("assembly", s, index=i) for i, s in enumerate((11, 12))]
    first = tmp_path / "policy"  # where the dashboard's first-network job writes
    if start == "unloadable":  # e.g. one of other configs: refused, then waited for again
        first.mkdir()
        (first / "policy.pt").write_bytes(b"not a checkpoint")
    dep = write_deployment(tmp_path / "d.toml", endpoint, {"policy": {"main": {
        "method": "learned", "checkpoint": str(first / "policy.pt"), "rate_hz": 5.0}}})
    svc = ServiceProcess("policy", dep, "main", tmp_path / "policy.log")
    plans, _sub = collect(session, f"{POLICY}/plan", "xm_msgs/msg/Plan")
    k = 0

    def health() -> dict:
        replies = query_json(session, f"{POLICY}/@health")
        return replies[0] if replies else {}

    def planned_by(method: str) -> bool:
        nonlocal k
        now = time.time()
        session.put("xm/world/sim/session", msgs.serialize(msgs.make(
            "xm_msgs/msg/Session", header=msgs.header(now), task="assembly", demo=0, phase="approach",
            tactile_hand="left", seed_layout="{}")))
        session.put("xm/recon/main/scene", _scene_msg(demos[0], k, now))
        k += 1
        return any(p.policy == method for p in plans)

    try:
        wait_until(lambda: health().get("waiting_for") == str(first / "policy.pt"), 60, svc.output)
        assert health()["method"] == "hold" and health()["status"] == "degraded"
        wait_until(lambda: planned_by("hold"), 30, lambda: f"plans holding the hands: {svc.output()}", period=0.1)
        save_demos(first / "demos", demos)  # the job writes its demonstrations first
        wait_until(lambda: planned_by("naive"), 30, lambda: f"the naive replay: {svc.output()}", period=0.1)
        assert health()["waiting_for"] == str(first / "policy.pt")
        train(preset("no_tactile", steps=20, hidden=(64, 64), batch=32, eval_every=10_000), demos, None, first,
              progress=False)  # then the checkpoint, in one rename
        wait_until(lambda: planned_by("learned:no_tactile"), 120, lambda: f"the network's plans: {svc.output()}",
                   period=0.1)
        now = health()
        assert now["status"] == "ok" and now["checkpoint"] == str(first / "policy.pt") and now["waiting_for"] is None
    finally:
        svc.stop()
