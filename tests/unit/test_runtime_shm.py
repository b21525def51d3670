"""Large payloads through the shared-memory pool (shared/runtime/shm.py), and the copies that
replace it, counted, when the pool cannot be opened or is full."""

from __future__ import annotations

import asyncio
import time

import numpy as np
import pytest

from shared import msgs
from shared.runtime import Node, fifo, open_client, shm
from tests.conftest import wait_until_async

KEY = "xm/bench/src/frame"
IMAGE = "sensor_msgs/msg/Image"
N = 12


def frame(i: int) -> object:
    data = np.random.default_rng(i).integers(0, 256, 480 * 640, dtype=np.uint8)  # 300 kB
    return msgs.make(IMAGE, header=msgs.header(time.time(), "cam0"), height=480, width=640, encoding="mono8",
                     is_bigendian=0, step=640, data=data)


def send_frames(endpoint: str) -> tuple[list, dict, int, list, dict]:
    """Puts N frames through a router; (received, publisher's errors, frames put from the pool, sent,
    the publisher's @health "shm")."""
    async def go() -> tuple[list, dict, int, list, dict]:
        src = Node("bench", "src", open_client(endpoint))
        dst = Node("bench", "dst", open_client(endpoint))
        got: list = []
        dst.subscribe(KEY, got.append, fifo(), msgtype=IMAGE)
        pub = src.publisher(KEY, IMAGE, block=True)
        await asyncio.sleep(0.3)  # the subscription reaches the router
        sent = [frame(i) for i in range(N)]
        for msg in sent:
            pub.put(msg)
            await asyncio.sleep(0.01)
        await wait_until_async(lambda: len(got) == N, 20, lambda: f"{N} frames, got {len(got)}")
        errors, pool = dict(src.stats.errors), src.health()["shm"]
        for node in (src, dst):
            await node.close()
            node.session.close()
        return got, errors, pub.shm_sent, sent, pool

    return asyncio.run(go())


def assert_same_frames(got: list, sent: list) -> None:
    for a, b in zip(got, sent, strict=True):
        assert msgs.serialize(a, IMAGE) == msgs.serialize(b, IMAGE)


def test_large_payloads_go_through_the_pool_intact(router, monkeypatch):
    endpoint, _ = router
    monkeypatch.setattr(shm, "POOL", shm.Pool())
    got, errors, from_pool, sent, pool = send_frames(endpoint)
    assert_same_frames(got, sent)
    assert from_pool == N - errors.get(f"shm_exhausted:{KEY}", 0) > 0
    assert f"shm_unavailable:{KEY}" not in errors
    assert pool["pool"] == "open" and pool["sent"] == from_pool
    assert pool["fallbacks"] == ({"shm_exhausted": N - from_pool} if from_pool < N else {})


def test_without_shared_memory_frames_are_copied_and_counted(router, monkeypatch):
    endpoint, _ = router
    pool = shm.Pool()
    monkeypatch.setattr(pool, "_failed", "no /dev/shm")  # as when the pool could not be created
    monkeypatch.setattr(shm, "POOL", pool)
    got, errors, from_pool, sent, health = send_frames(endpoint)
    assert_same_frames(got, sent)
    assert from_pool == 0 and errors[f"shm_unavailable:{KEY}"] == N
    assert health["pool"] == "unavailable" and health["unavailable"] == "no /dev/shm"
    assert health["sent"] == 0 and health["fallbacks"] == {"shm_unavailable": N}


def test_a_full_pool_falls_back_to_copies_counted(router, monkeypatch):
    endpoint, _ = router
    monkeypatch.setattr(shm, "POOL", shm.Pool(size=256 * 1024))  # smaller than one frame
    got, errors, from_pool, sent, pool = send_frames(endpoint)
    assert_same_frames(got, sent)
    assert from_pool == 0 and errors[f"shm_exhausted:{KEY}"] == N
    assert pool["sent"] == 0 and pool["fallbacks"] == {"shm_exhausted": N}


@pytest.mark.parametrize(("size", "msgtype"), [(shm.MIN_BYTES - 1, "sensor_msgs/msg/CompressedImage"),
                                               (shm.MIN_BYTES, "sensor_msgs/msg/CompressedImage"),
                                               (shm.MIN_BYTES, "std_msgs/msg/UInt8MultiArray")])
def test_put_bytes_uses_the_pool_from_the_threshold_for_sensor_types(router, monkeypatch, size, msgtype):
    endpoint, _ = router
    monkeypatch.setattr(shm, "POOL", shm.Pool())

    async def go() -> tuple[list, int]:
        src = Node("bench", "src", open_client(endpoint))
        dst = Node("bench", "dst", open_client(endpoint))
        got: list = []
        dst.subscribe(KEY, got.append, fifo(), msgtype="raw")
        pub = src.publisher(KEY, msgtype)
        await asyncio.sleep(0.3)
        pub.put_bytes(bytes(range(256)) * (size // 256) + b"x" * (size % 256))
        await wait_until_async(lambda: got, 10, "the payload")
        for node in (src, dst):
            await node.close()
            node.session.close()
        return got, pub.shm_sent

    got, from_pool = asyncio.run(go())
    assert len(got[0]) == size and got[0][:3] == b"\x00\x01\x02"
    assert from_pool == (size >= shm.MIN_BYTES and msgtype in shm.POOL_TYPES)
