"""Time that jumps back, validation of every registered type, rate-limited warnings (pure)."""

from __future__ import annotations

import asyncio
import logging

import numpy as np
import pytest

from shared import keys, msgs
from shared.runtime import validate
from shared.runtime.clock import Clock
from shared.runtime.logs import RateLimitedLog
from tests.bad_messages import bad_payloads, good


def test_sim_ticks_rebase_when_the_world_restarts():
    async def go() -> tuple[list[float], Clock, list]:
        clock = Clock("sim")
        jumps: list[tuple[float, float]] = []
        clock.on_jump(lambda old, new: jumps.append((old, new)))
        seen: list[float] = []

        async def loop() -> None:
            async for t in clock.ticks(10.0):
                seen.append(t)

        clock.advance(150.0)
        task = asyncio.ensure_future(loop())
        for i in range(1, 11):  # one simulated second on the old timeline
            clock.advance(150.0 + i * 0.1)
            await asyncio.sleep(0)
        for i in range(11):  # the world restarts at 0
            clock.advance(i * 0.1)
            await asyncio.sleep(0)
        task.cancel()
        return seen, clock, jumps

    seen, clock, jumps = asyncio.run(go())
    assert clock.jumps == 1 and jumps == [(151.0, 0.0)]
    after = [t for t in seen if t < 100]
    assert after and after[0] == 0.0, seen  # the first tick of the new timeline comes at once
    assert after[-1] == pytest.approx(1.0)  # and the loop keeps its rate on it
    assert len(after) >= 10


def test_small_steps_back_are_jitter_not_a_restart():
    clock = Clock("sim")
    clock.advance(10.0)
    clock.advance(9.5)
    assert clock.jumps == 0


def test_wall_ticks_rebase_when_the_host_clock_is_stepped_back(monkeypatch):
    fake = [1000.0]
    monkeypatch.setattr("shared.runtime.clock.time.time", lambda: fake[0])

    async def go() -> list[float]:
        clock = Clock("wall")
        seen: list[float] = []
        async for t in clock.ticks(100.0):
            seen.append(t)
            fake[0] = 500.0 if len(seen) == 3 else fake[0] + 0.01
            if len(seen) == 6:
                break
        assert clock.jumps == 1
        return seen

    seen = asyncio.run(go())
    assert seen[:3] == pytest.approx([1000.0, 1000.01, 1000.02])
    assert seen[3] == 500.0 and seen[5] < 501.0


def test_stamps_are_checked_against_the_newest_clock_sample_while_the_loop_is_busy():
    async def go() -> list:
        loop = asyncio.get_running_loop()
        clock = Clock("sim")
        assert clock.reference() is None  # not started: stamps are not checked
        clock.observe(10.0, loop)
        clock.observe(12.5, loop)  # the loop has not run yet: the time is not advanced
        during = (clock.now(), clock.reference())
        msg = good("xm_msgs/msg/Tactile", 12.4)  # fresh, though 2.4 s ahead of the advanced time
        validate.check(msg, "xm_msgs/msg/Tactile", clock.reference())
        await asyncio.sleep(0)  # the loop catches up once, with the newest sample
        after = (clock.now(), clock.reference())
        clock.observe(0.2, loop)  # the world restarts: older stamps are from another timeline at once
        with pytest.raises(validate.RejectedError, match="ahead"):
            validate.check(msg, "xm_msgs/msg/Tactile", clock.reference())
        await asyncio.sleep(0)
        return [during, after, clock.jumps]

    during, after, jumps = asyncio.run(go())
    assert during == (0.0, 12.5)
    assert after == (12.5, 12.5)
    assert jumps == 1


@pytest.mark.parametrize("spec", keys.REGISTRY, ids=lambda s: s.key)
def test_every_kind_of_bad_message_is_rejected_with_its_reason(spec):
    now = 1000.0
    msgtype = spec.msgtype
    ok = msgs.serialize(good(msgtype, now), msgtype)
    validate.check(msgs.deserialize(ok, msgtype), msgtype, now)  # the sample itself is fine
    bad = bad_payloads(msgtype, now)
    assert {"malformed", "oversized"} <= set(bad)
    for reason, payload in bad.items():
        with pytest.raises((validate.RejectedError, msgs.MessageError)) as err:
            validate.check_size(len(payload), msgtype)
            validate.check(msgs.deserialize(payload, msgtype), msgtype, now)
        got = err.value.reason if isinstance(err.value, validate.RejectedError) else "malformed"
        assert got == reason, (msgtype, reason, str(err.value))


def test_types_with_floats_or_arrays_get_the_nan_and_length_checks():
    kinds = {spec.msgtype: set(bad_payloads(spec.msgtype, 0.0)) for spec in keys.REGISTRY}
    for msgtype in ("xm_msgs/msg/Plan", "xm_msgs/msg/Scene", "sensor_msgs/msg/JointState", "xm_msgs/msg/Tactile",
                    "trajectory_msgs/msg/JointTrajectory", "xm_msgs/msg/GroundTruth"):
        assert {"non_finite", "bad_length", "stale_stamp", "future_stamp"} <= kinds[msgtype], msgtype


def test_stamps_are_not_checked_before_the_clock_started():
    msg = good("xm_msgs/msg/Tactile", 5000.0)
    validate.check(msg, "xm_msgs/msg/Tactile", None)
    with pytest.raises(validate.RejectedError, match="ahead"):
        validate.check(msg, "xm_msgs/msg/Tactile", 0.0)


def test_nan_plans_all_or_half_are_rejected_by_trajopt_mapping():
    from services.trajopt.mapping import plan_arrays

    for share in (1.0, 0.5):
        plan = good("xm_msgs/msg/Plan", 0.0)
        pos = np.zeros((2, 1, 3), np.float32)
        pos[: max(1, int(2 * share))] = np.nan
        plan.positions = pos.ravel()
        with pytest.raises(ValueError, match="non-finite"):
            plan_arrays(plan)


def test_rate_limited_log_writes_the_first_then_a_summary(caplog):
    log = logging.getLogger("xm.test.ratelimit")
    limited = RateLimitedLog(log, every_s=0.0 + 3600)
    with caplog.at_level(logging.WARNING, logger="xm.test.ratelimit"):
        for _ in range(1000):
            limited.warning("malformed:k", "rejected message", key="k")
        limited.warning("other", "another kind")
        assert len(caplog.records) == 2
        limited.every_s = 0.0
        limited.flush()
    assert len(caplog.records) == 3 and "999 more" in caplog.records[-1].getMessage()


def test_a_healthy_child_is_restarted_at_once_and_a_failing_one_backs_off():
    from deploy.supervisor import BACKOFF_MAX_S, backoff_delay

    assert backoff_delay(1) == 0.0
    delays = [backoff_delay(n) for n in range(2, 12)]
    assert delays[0] > 0 and delays == sorted(delays) and delays[-1] == BACKOFF_MAX_S


def test_supervisor_child_states():
    from deploy.supervisor import Child

    class Proc:
        returncode = None
        pid = 1

    child = Child("recon", "main")
    assert child.state == "restarting"  # no process
    child.proc = Proc()
    assert child.state == "starting"
    child.restarts = 1
    assert child.state == "recovering"
    child.alive = True
    assert child.state == "ok"


def test_status_line_sums_rejections_by_reason_and_drops():
    from deploy.supervisor import counted

    h = {"rejected": {"a": {"malformed": 2, "non_finite": 1}, "b": {"malformed": 3}}, "dropped": {"a": 4, "b": 1}}
    assert counted(h) == " | rejected=6 (malformed=5, non_finite=1) dropped=5"
    assert counted({"rejected": {}, "dropped": {}}) == ""



@pytest.mark.parametrize("spec", keys.REGISTRY, ids=lambda s: s.key)
def test_the_per_type_finite_check_finds_what_a_full_walk_finds(spec):
    """Every float field of every registered type, set to NaN in turn: the checker built from the
    type's definition names it, as walking the whole message does."""
    msg = good(spec.msgtype, 1000.0)
    assert validate._first_non_finite(msg, spec.msgtype) is None
    found = 0
    for owner, name in float_fields(msg):
        value = getattr(owner, name)
        if isinstance(value, np.ndarray):
            if not len(value):
                continue
            bad = value.copy()
            bad[-1] = np.nan
        else:
            bad = float("inf")
        setattr(owner, name, bad)
        path = validate._first_non_finite(msg, spec.msgtype)
        assert path is not None and path.endswith(name), (spec.msgtype, name, path)
        assert validate._walk_non_finite(msg, spec.msgtype) is not None
        setattr(owner, name, value)
        found += 1
    assert validate._first_non_finite(msg, spec.msgtype) is None


def float_fields(msg) -> list:
    """(object, field name) of every float scalar or float array in a message, nested ones included."""
    out = []
    for name in getattr(msg, "__dataclass_fields__", {}):
        if name == "__msgtype__":
            continue
        value = getattr(msg, name)
        if isinstance(value, float) or (isinstance(value, np.ndarray) and value.dtype.kind == "f"):
            out.append((msg, name))
        elif isinstance(value, list):
            for item in value:
                out += float_fields(item)
        else:
            out += float_fields(value)
    return out
