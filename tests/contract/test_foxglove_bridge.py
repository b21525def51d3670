"""The Foxglove bridge as a process: a WebSocket client speaking the Foxglove protocol
(subprotocol foxglove.sdk.v1) sees our keys advertised with their .msg schemas, subscribes and decodes
the CDR it receives; hands, objects and robot links arrive as scene entities and transforms."""

from __future__ import annotations

import asyncio
import json
import struct
import time

import numpy as np
import websockets

from shared import msgs
from shared.kinematics import load_robot
from tests.conftest import ServiceProcess, free_port, query_json, wait_for, wait_until_async, write_deployment

SUBPROTOCOL = "foxglove.sdk.v1"  # the SDK server accepts only this name of the protocol
MESSAGE_DATA = 0x01  # binary opcode: u32 subscription id, u64 receive time, payload


def scene(t: float) -> bytes:
    kp = np.linspace(0.0, 0.3, 126, dtype=np.float32)
    mask = np.ones(42, np.uint8)
    mask[5] = 0
    return msgs.serialize(msgs.make(
        "xm_msgs/msg/Scene", header=msgs.header(t), hand_names=["left", "right"], hand_keypoints=kp,
        hand_mask=mask, object_names=["lens/center", "lens/edge"], object_keypoints=np.zeros(6, np.float32),
        object_mask=np.ones(2, np.uint8), tactile_regions=[], tactile=np.zeros(0, np.float32),
        tactile_mask=np.zeros(0, np.uint8)))


def joints(t: float) -> bytes:
    names = load_robot("workcell").joint_names
    return msgs.serialize(msgs.make("sensor_msgs/msg/JointState", header=msgs.header(t), name=names,
                                    position=np.full(len(names), 0.01), velocity=np.zeros(len(names)),
                                    effort=np.zeros(len(names))))


class Client:
    """The protocol's client side: advertisements in, subscriptions out, message data in."""

    def __init__(self, ws) -> None:
        self.ws = ws
        self.channels: dict[str, dict] = {}  # topic -> advertised channel
        self.subs: dict[int, str] = {}  # subscription id -> topic
        self.received: dict[str, list[bytes]] = {}

    async def pump(self) -> None:
        async for frame in self.ws:
            if isinstance(frame, str):
                op = json.loads(frame)
                if op["op"] == "advertise":
                    self.channels |= {c["topic"]: c for c in op["channels"]}
            elif frame[0] == MESSAGE_DATA:
                sub, _t = struct.unpack_from("<IQ", frame, 1)
                self.received.setdefault(self.subs[sub], []).append(bytes(frame[13:]))

    async def subscribe(self, topic: str) -> None:
        sid = len(self.subs) + 1
        self.subs[sid] = topic
        await self.ws.send(json.dumps({"op": "subscribe", "subscriptions": [
            {"id": sid, "channelId": self.channels[topic]["id"]}]}))


def test_bridge_forwards_keys_and_draws_the_scene(router, tmp_path):
    endpoint, session = router
    port = free_port()
    dep = write_deployment(tmp_path / "d.toml", endpoint, {"foxglove": {"main": {
        "port": port, "keys": ["xm/recon/main/scene", "xm/robot/*/state", "xm/nothing/here"]}}})
    svc = ServiceProcess("foxglove", dep, "main", tmp_path / "foxglove.log")
    pubs = {k: session.declare_publisher(k) for k in ("xm/recon/main/scene", "xm/robot/workcell/state")}

    def publish() -> None:
        t = time.time()
        pubs["xm/recon/main/scene"].put(scene(t))
        pubs["xm/robot/workcell/state"].put(joints(t))

    async def run() -> Client:
        deadline = time.monotonic() + 60
        while True:  # the service imports, connects to the router, then listens
            try:
                ws = await websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL])
                break
            except OSError:
                assert time.monotonic() < deadline, f"no WebSocket server on {port}:\n{svc.output()}"
                await asyncio.sleep(0.2)
        async with ws:
            assert ws.subprotocol == SUBPROTOCOL
            client = Client(ws)
            pump = asyncio.create_task(client.pump())

            def advertised() -> bool:
                publish()
                return {"xm/recon/main/scene", "xm/robot/workcell/state", "/xm/scene", "/tf"} <= set(client.channels)
            await wait_until_async(advertised, 30, lambda: f"advertised {sorted(client.channels)}", 0.1)
            for topic in ("xm/recon/main/scene", "/xm/scene", "/tf"):
                await client.subscribe(topic)

            def got() -> bool:
                publish()
                return all(client.received.get(t) for t in ("xm/recon/main/scene", "/xm/scene", "/tf"))
            await wait_until_async(got, 30, lambda: f"received {list(client.received)}", 0.1)
            pump.cancel()
            return client

    try:
        client = asyncio.run(run())
        ch = client.channels["xm/recon/main/scene"]
        assert (ch["encoding"], ch["schemaName"], ch["schemaEncoding"]) == ("cdr", "xm_msgs/msg/Scene", "ros2msg")
        assert ch["schema"] == msgs.schema_text("xm_msgs/msg/Scene")
        got = msgs.deserialize(client.received["xm/recon/main/scene"][0], "xm_msgs/msg/Scene")
        np.testing.assert_array_equal(got.hand_keypoints, np.linspace(0.0, 0.3, 126, dtype=np.float32))
        assert client.channels["/xm/scene"]["schemaName"] == "foxglove.SceneUpdate"
        update = client.received["/xm/scene"][-1]
        assert b"hand/left" in update and b"hand/right" in update and b"object/lens" in update
        assert client.channels["/tf"]["schemaName"] == "foxglove.FrameTransforms"
        assert b"world" in client.received["/tf"][-1]
        junk = session.declare_publisher("xm/nothing/here")  # matches `keys`, but no service declares it

        def counted() -> list[dict]:
            junk.put(b"junk")
            return [h for h in _health(session) if h.get("errors", {}).get("unregistered_key:xm/nothing/here")]
        health = wait_for(counted, 30)
        assert health and health[0]["url"] == f"ws://127.0.0.1:{port}"
        forwarded = health[0]["forwarded"]
        assert forwarded.get("xm/recon/main/scene", 0) > 0 and "xm/nothing/here" not in forwarded
    finally:
        assert svc.stop(timeout=30) in (0, -15), svc.output()  # a loaded host can take seconds to exit


def _health(session) -> list[dict]:
    return query_json(session, "xm/foxglove/main/@health")
