"""Helpers of the recorder service: file names, key filters, health counters, and a recording's
queue between Zenoh's thread and the writer (without Zenoh)."""

from __future__ import annotations

import logging
from collections import Counter

import numpy as np
import pytest
from mcap_ros2.reader import read_ros2_messages

from services.recorder import service
from services.recorder.service import Recording, check_pattern, default_path, dropped
from shared import msgs
from shared.keys import is_internal
from shared.runtime.stats import Stats


def test_default_path_is_timestamped_and_never_reuses_a_name(tmp_path):
    first = default_path(tmp_path, now=0.0)
    assert first.parent == tmp_path and first.name.startswith("xm-") and first.suffix == ".mcap"
    first.write_bytes(b"")
    second = default_path(tmp_path, now=0.0)
    assert second != first and second.name == first.stem + "-2.mcap"


def test_at_keys_are_internal_wherever_the_chunk_is():
    assert is_internal("xm/glove/left/@health") and is_internal("xm/recorder/main/@cmd/start")
    assert is_internal("@/session/x") and not is_internal("xm/glove/left/tactile")
    assert not is_internal("xm/a@b/c")  # only a chunk starting with @ is verbatim-internal


def test_patterns_are_checked_before_any_file_is_opened():
    assert check_pattern("xm/glove/*/tactile") == "xm/glove/*/tactile"
    for bad in ("xm//x", "xm/a/", "other/**"):
        with pytest.raises(ValueError, match="keys"):
            check_pattern(bad)


def test_dropped_groups_node_error_counters_by_kind_and_key():
    errors = Counter({"unregistered_key:xm/odd": 3, "bad_payload:xm/clock": 2, "queue_overflow": 4,
                      "handler_error:xm/clock": 1})
    assert dropped(errors) == {"unregistered_key": {"xm/odd": 3}, "bad_payload": {"xm/clock": 2},
                               "queue_overflow": 4}


class FakeNode:
    """What a Recording uses of a node: subscribe (the handler is called by the test), spawn, counters."""

    def __init__(self) -> None:
        self.stats = Stats()
        self.log = logging.getLogger("xm")
        self.handler = None
        self.history: dict[str, bool] = {}
        self.failed: list = []

    def subscribe(self, pattern, handler, _policy, msgtype=None, inline=False, history=False):
        assert msgtype == "raw" and inline  # stamped on Zenoh's thread, no loop hop per message
        self.history[pattern] = history  # only states: a recording starts with each one's latest message
        if not history:
            self.handler = handler
        return self

    def spawn(self, coro, name=None):
        coro.close()  # the test drains by hand
        return self

    def handler_failed(self, key, exc) -> None:
        self.failed.append((key, exc))

    def set_status(self, *_args) -> None:
        pass


def tactile(i: int) -> bytes:
    return msgs.serialize(msgs.make(
        "xm_msgs/msg/Tactile", header=msgs.header(10.0 + i, "glove_left"), hand="left", rows=16, cols=16,
        pressure=np.full(256, float(i), np.float32), mask=np.ones(256, np.uint8), sequence=i))


def test_a_recording_writes_in_arrival_order_with_receive_times_and_counts_what_it_refuses(tmp_path, monkeypatch):
    monkeypatch.setattr(service, "MAX_PENDING", 5)
    node = FakeNode()
    rec = Recording(node, tmp_path / "q.mcap", "xm/**", {}, segment_s=0)
    assert node.history == {"xm/**": False, "xm/world/*/session": True}, "history for the states only"
    key = "xm/glove/left/tactile"
    for i in range(4):
        node.handler(tactile(i), key)
    node.handler(b"\x00\x01\x00\x00bad", key)
    node.handler(b"x", "xm/not/registered")  # the queue is full now: refused, counted
    node.handler(tactile(9), key)
    rec.write_pending()
    node.handler(b"x", "xm/not/registered")
    node.handler(b"x", "xm/recorder/main/@health")
    rec.write_pending()
    rec.closed = True
    node.handler(tactile(10), key)  # after stop: counted as late, not written
    rec.writer.close()
    assert node.stats.errors == Counter({"queue_overflow": 2, f"bad_payload:{key}": 1,
                                         "unregistered_key:xm/not/registered": 1})
    assert rec.malformed == {key: 1} and rec.unknown == {"xm/not/registered": 1} and rec.late == 1
    assert not node.failed
    got = list(read_ros2_messages(str(tmp_path / "q.mcap")))
    assert [m.ros_msg.sequence for m in got] == [0, 1, 2, 3]
    times = [m.log_time_ns for m in got]
    assert times == sorted(times) and len(set(times)) == 4  # each its own receive time
