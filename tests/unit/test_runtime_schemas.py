"""A subscriber refuses a key whose publisher declares another message type or schema
(shared/runtime/schemas.py), at subscription time and when the publisher comes later, and accepts
it again when that publisher goes."""

from __future__ import annotations

import asyncio

from shared import msgs
from shared.runtime import Node, fifo, open_client, schemas
from tests.conftest import wait_until_async

KEY = "xm/bench/src/value"
STRING = "std_msgs/msg/String"
FLOAT = "std_msgs/msg/Float64"


def test_tokens_name_the_type_and_its_schema():
    token = schemas.token_key(KEY, "sensor_msgs/msg/JointState")
    declared = schemas.parse_token(token)
    joint_state = "sensor_msgs/msg/JointState"
    assert declared == schemas.Declared(KEY, joint_state, schemas.type_hash(joint_state))
    assert schemas.mismatch(declared, "sensor_msgs/msg/JointState") is None
    assert "expects std_msgs/msg/String" in schemas.mismatch(declared, STRING)
    stale = schemas.Declared(KEY, STRING, "0123456789abcdef")
    assert "different .msg definitions" in schemas.mismatch(stale, STRING)
    assert schemas.parse_token("xm/robot/workcell/state") is None
    assert schemas.type_hash(STRING) != schemas.type_hash(FLOAT)


def test_a_publisher_of_another_type_is_refused_and_counted(router):
    endpoint, _ = router

    async def go() -> None:
        src = Node("bench", "src", open_client(endpoint))
        dst = Node("bench", "dst", open_client(endpoint))
        got: list = []
        wrong = src.publisher(KEY, STRING)  # declared before the subscription: refused at subscription time
        sub = dst.subscribe(KEY, got.append, fifo(), msgtype=FLOAT)
        await wait_until_async(lambda: KEY in sub.refused, 10, "the mismatch to be seen")
        assert "sends std_msgs/msg/String" in next(iter(sub.refused[KEY].values()))
        def refused() -> int:
            return dst.stats.rejected.get(KEY, {}).get("type_mismatch", 0)

        # The type token can arrive before the data route exists: publish until the first is heard.
        deadline = asyncio.get_running_loop().time() + 10
        while not refused() and asyncio.get_running_loop().time() < deadline:
            wrong.put(msgs.make(STRING, data="not a float"))
            await asyncio.sleep(0.05)
        before = refused()
        for _ in range(3):
            wrong.put(msgs.make(STRING, data="not a float"))
        await wait_until_async(lambda: refused() >= before + 3, 10, "three more refused samples")
        assert got == [] and dst.stats.errors[f"type_mismatch_publisher:{KEY}"] == 1
        # The wrong publisher goes; a right one comes later and is heard.
        wrong._type_token.undeclare()
        await wait_until_async(lambda: KEY not in sub.refused, 10, "the key to be accepted again")
        right = src.publisher(KEY, FLOAT)
        await asyncio.sleep(0)
        right.put(msgs.make(FLOAT, data=2.5))
        await wait_until_async(lambda: got, 10, "the right type's sample")
        assert got[0].data == 2.5 and KEY not in sub.refused
        for node in (src, dst):
            await node.close()
            node.session.close()

    asyncio.run(go())


def test_a_publisher_of_the_same_type_with_another_schema_is_refused(router):
    """Two builds with different .msg files under one type name: the token's schema hash differs."""
    endpoint, _ = router

    async def go() -> None:
        other_build = open_client(endpoint)
        token = other_build.liveliness().declare_token(f"{KEY}/@type/std_msgs~msg~Float64~0123456789abcdef")
        dst = Node("bench", "dst", open_client(endpoint))
        sub = dst.subscribe(KEY, lambda _m: None, fifo(), msgtype=FLOAT, inline=True)
        await wait_until_async(lambda: KEY in sub.refused, 10, "the schema mismatch to be seen")
        assert "different .msg definitions" in next(iter(sub.refused[KEY].values()))
        token.undeclare()
        await wait_until_async(lambda: KEY not in sub.refused, 10, "the key to be accepted again")
        await dst.close()
        dst.session.close()
        other_build.close()

    asyncio.run(go())


def test_track_keeps_each_key_while_one_of_its_publishers_lives():
    from shared.runtime.schemas import track

    live: dict[str, set[str]] = {}
    track(live, "xm/camhub/cam0/info", "t1", gone=False)
    track(live, "xm/camhub/cam0/info", "t2", gone=False)  # a restarted publisher before the old one's token went
    track(live, "xm/camhub/cam0/info", "t1", gone=True)
    assert live == {"xm/camhub/cam0/info": {"t2"}}
    track(live, "xm/camhub/cam0/info", "t2", gone=True)
    assert live == {}
