"""Every bad message on every registered key is counted with its reason, and what a queue policy
discards is counted too: sent == rejected (by reason) + dropped by the queue, per key."""

from __future__ import annotations

import asyncio
import collections
import logging
import threading
import time

import numpy as np
import pytest
import zenoh

from shared import keys, msgs
from shared.kinematics import load_robot
from shared.runtime import Node, fifo, latest, open_client
from tests.bad_messages import bad_payloads, good
from tests.conftest import ServiceProcess, query_json, wait_for, write_deployment

pytestmark = pytest.mark.slow


async def wait_until(predicate, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        await asyncio.sleep(0.05)
    return predicate()


def publish(session, sends: list[tuple[str, bytes]]) -> None:
    pubs = {}
    for key, payload in sends:
        if key not in pubs:  # blocking: this test counts delivery, the publisher must not drop
            pubs[key] = session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
        pubs[key].put(payload)
    for pub in pubs.values():
        pub.undeclare()


def probe(endpoint: str, router_session, policy, sends_at, inline: bool = False) -> dict:
    """Runs a node subscribed to every key with ``policy``, publishes ``sends_at(now)`` from the
    router's session, waits until every message is accounted for; returns its health report and
    what was sent per key."""
    async def go() -> tuple[dict, collections.Counter]:
        client = open_client(endpoint)
        node = Node("probe", "test", client, "wall")
        delivered: collections.Counter[str] = collections.Counter()
        loop_thread = threading.get_ident()

        def handle(_msg, key: str) -> None:
            delivered.update([key])
            delivered["(on the loop's thread)"] += threading.get_ident() == loop_thread

        node.subscribe("xm/**", handle, policy, inline=inline)
        try:
            await asyncio.sleep(0.5)  # the subscription reaches the router
            sends = sends_at(time.time())
            sent = collections.Counter(k for k, _ in sends)
            await asyncio.to_thread(publish, router_session, sends)

            def accounted() -> bool:
                h = node.health()
                return all(sum(h["rejected"].get(k, {}).values()) + h["dropped"].get(k, 0) + delivered[k] >= n
                           for k, n in sent.items())

            await wait_until(accounted, 30)
            return node.health(), sent, delivered
        finally:
            await node.close()
            client.close()

    health, sent, delivered = asyncio.run(go())
    on_loop = delivered.pop("(on the loop's thread)", 0)
    return {"health": health, "sent": sent, "delivered": +delivered, "on_loop": on_loop}


def test_each_kind_of_bad_message_on_every_registered_key_is_counted_with_its_reason(router):
    endpoint, session = router
    expected: dict[str, dict[str, int]] = {}

    def sends_at(now: float) -> list[tuple[str, bytes]]:
        out = []
        for spec in keys.REGISTRY:
            for reason, payload in bad_payloads(spec.msgtype, now).items():
                n = 1 if reason == "oversized" else 3
                out += [(spec.key, payload)] * n
                expected.setdefault(spec.key, {})[reason] = n
        return out

    got = probe(endpoint, session, fifo(), sends_at)
    h = got["health"]
    assert not got["delivered"], got["delivered"]  # nothing bad reached a handler
    assert h["dropped"] == {}
    for key, reasons in expected.items():
        assert h["rejected"].get(key) == reasons, (key, h["rejected"].get(key))


def test_inline_subscriptions_count_every_bad_message_and_deliver_good_ones_on_zenohs_thread(router):
    endpoint, session = router
    expected: dict[str, dict[str, int]] = {}
    good_key = keys.REGISTRY[0]

    def sends_at(now: float) -> list[tuple[str, bytes]]:
        out = []
        for spec in keys.REGISTRY:
            for reason, payload in bad_payloads(spec.msgtype, now).items():
                out += [(spec.key, payload)] * 2
                expected.setdefault(spec.key, {})[reason] = 2
        out += [(good_key.key, msgs.serialize(good(good_key.msgtype, now), good_key.msgtype))] * 5
        return out

    got = probe(endpoint, session, fifo(), sends_at, inline=True)
    h = got["health"]
    assert got["delivered"] == {good_key.key: 5}
    assert got["on_loop"] == 0  # every one handled on a Zenoh thread
    assert h["dropped"] == {}
    for key, reasons in expected.items():
        assert h["rejected"].get(key) == reasons, (key, h["rejected"].get(key))


def test_an_inline_handler_must_be_a_plain_function(router):
    endpoint, _session = router

    async def handler(_msg) -> None:
        pass

    async def go() -> None:
        client = open_client(endpoint)
        node = Node("probe", "inline", client, "wall")
        try:
            with pytest.raises(TypeError, match="plain function"):
                node.subscribe("xm/clock", handler, inline=True)
        finally:
            await node.close()
            client.close()

    asyncio.run(go())


def test_a_flood_of_garbage_is_counted_to_the_last_message_on_keep_latest_queues(router, caplog):
    endpoint, session = router
    per_key = 1500

    def sends_at(now: float) -> list[tuple[str, bytes]]:
        kinds = {s.key: [p for r, p in bad_payloads(s.msgtype, now).items() if r != "oversized"]
                 for s in keys.REGISTRY}
        return [(k, kinds[k][i % len(kinds[k])]) for i in range(per_key) for k in kinds]

    with caplog.at_level(logging.WARNING, logger="xm"):
        got = probe(endpoint, session, latest(1), sends_at)
    h = got["health"]
    kinds = sum(len(reasons) for reasons in h["rejected"].values())
    lines = [r for r in caplog.records if r.getMessage().startswith("rejected message")]
    assert kinds <= len(lines) <= 2 * kinds  # the first of each kind, then at most a summary each
    assert not got["delivered"]
    for spec in keys.REGISTRY:
        rejected = sum(h["rejected"].get(spec.key, {}).values())
        assert rejected + h["dropped"].get(spec.key, 0) == per_key, (spec.key, h["rejected"].get(spec.key),
                                                                    h["dropped"].get(spec.key))
        assert rejected >= 1  # the last one at least was decoded and judged
        assert h["arrived"][spec.key] == per_key


def test_trajopt_rejects_plans_with_nan_keypoints_with_a_reason_and_a_counter(router, tmp_path):
    endpoint, session = router
    dep = write_deployment(tmp_path / "d.toml", endpoint, {"trajopt": {"main": {}}})
    names = load_robot("workcell").joint_names
    with ServiceProcess("trajopt", dep, "main", tmp_path / "trajopt.log") as trajopt:
        assert wait_for(lambda: query_json(session, "xm/trajopt/main/@health"), 60), trajopt.output()
        for share in (1.0, 0.5):  # every keypoint NaN, then half of them
            def counted(share: float = share) -> bool:
                now = time.time()
                session.put("xm/robot/workcell/state", msgs.serialize(msgs.make(
                    "sensor_msgs/msg/JointState", header=msgs.header(now), name=names, position=np.zeros(len(names)),
                    velocity=np.zeros(len(names)), effort=np.zeros(len(names)))))
                pos = np.full((11, 2, 3), 0.1, np.float32)
                pos[: int(round(11 * share))] = np.nan
                session.put("xm/policy/main/plan", msgs.serialize(msgs.make(
                    "xm_msgs/msg/Plan", header=msgs.header(now), policy="test", dt=0.1, steps=11,
                    point_names=["left/4", "left/8"], positions=pos.ravel(), mask=np.ones(22, np.uint8),
                    efforts=np.zeros(0, np.float32))))
                h = query_json(session, "xm/trajopt/main/@health")
                n = h[0]["rejected"].get("xm/policy/main/plan", {}).get("non_finite", 0) if h else 0
                return n >= (1 if share == 1.0 else 2) and h[0]

            h = wait_for(counted, 20)
            assert h, trajopt.output()
        assert "rejected message" in trajopt.output() and "non_finite" in trajopt.output()
