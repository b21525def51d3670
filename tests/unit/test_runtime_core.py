"""Pure parts of the runtime: key registry, deployment parsing, messages, clock."""

from __future__ import annotations

import asyncio
import threading
from dataclasses import dataclass

import numpy as np
import pytest

from shared import keys, msgs
from shared.config import ConfigError, load_deployment, parse_params
from shared.runtime.clock import Clock
from shared.runtime.node import RateMeter


def test_every_registered_type_exists_and_round_trips():
    for spec in keys.REGISTRY:
        cls = msgs.msg_class(spec.msgtype)
        assert cls.__msgtype__ == spec.msgtype
        assert "MSG:" in msgs.schema_text(spec.msgtype) or spec.msgtype.startswith("rosgraph")


def test_tactile_round_trip_and_garbage_rejected():
    m = msgs.make("xm_msgs/msg/Tactile", header=msgs.header(12.25, "glove"), hand="right", rows=16, cols=16,
                  pressure=np.arange(256, dtype=np.float32), mask=np.ones(256, np.uint8), sequence=7)
    back = msgs.deserialize(msgs.serialize(m), "xm_msgs/msg/Tactile")
    assert back.hand == "right" and back.sequence == 7
    assert msgs.stamp_seconds(back.header.stamp) == pytest.approx(12.25)
    np.testing.assert_array_equal(back.pressure, m.pressure)
    with pytest.raises(msgs.MessageError):
        msgs.deserialize(b"\x00\x01\x00\x00garbage", "xm_msgs/msg/Tactile")


def test_key_patterns():
    assert keys.key_matches("xm/**", "xm/glove/left/tactile")
    assert keys.key_matches("xm/*/left/*", "xm/glove/left/tactile")
    assert not keys.key_matches("xm/camhub/*/image", "xm/camhub/cam0/info")
    assert len(keys.matching("xm/camhub/*/image")) == len(keys.CAMERAS)
    assert keys.msgtype_of("xm/glove/left/raw") == "xm_msgs/msg/TactileRaw"
    assert keys.msgtype_of("xm/nothing/here") is None


def test_sim_deployment_loads_and_covers_every_publishing_service():
    dep = load_deployment("deploy/sim.toml")
    publishing = {spec.service for spec in keys.REGISTRY}
    assert publishing <= set(dep.services)
    assert dep.params("glove", "left")["port"] == "/tmp/xm-sim/glove-left"


def test_hand_arm_deployment_names_one_robot_everywhere():
    """deploy/hand_arm.toml: world, trajopt, robot and panel all run the hand-arm model (the
    deployment's `robot`, the default of their `robot` parameter), the robot
    service's instance carries the model's name (so its state key is the one trajopt and panel read),
    and every parameter is one the services know."""
    from services.panel.service import PanelService
    from services.robot.service import RobotService
    from services.trajopt.service import TrajoptService
    from services.world.service import WorldService

    dep = load_deployment("deploy/hand_arm.toml")
    assert dep.robot == "hand_arm"
    assert {spec.service for spec in keys.REGISTRY} <= set(dep.services)
    classes = {"world": WorldService, "trajopt": TrajoptService, "robot": RobotService, "panel": PanelService}
    robots = {}
    for service, cls in classes.items():
        (instance,) = dep.services[service]
        robots[service] = dep.service_params(cls.Params, service, instance).robot
    assert set(robots.values()) == {"hand_arm"} and list(dep.services["robot"]) == ["hand_arm"]
    assert keys.robot_state_key("hand_arm") == "xm/robot/hand_arm/state"
    assert keys.msgtype_of(keys.robot_state_key("hand_arm")) == "sensor_msgs/msg/JointState"
    assert keys.robot_state_key("workcell") in keys.BY_KEY  # the default deployment's key is unchanged


def test_bad_deployments_name_file_key_and_type(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text('[deployment]\nname = 3\n')
    with pytest.raises(ConfigError, match=r"bad.toml: deployment.name: expected str, got int"):
        load_deployment(bad)
    bad.write_text('[deployment]\n[services.teleporter.main]\n')
    with pytest.raises(ConfigError, match="unknown service.*known: camhub, .*glove.*world"):
        load_deployment(bad)
    bad.write_text('[deployment\n')
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_deployment(bad)
    with pytest.raises(ConfigError, match="not found"):
        load_deployment(tmp_path / "missing.toml")


def test_parse_params_checks_types_and_unknown_keys():
    @dataclass
    class P:
        rate_hz: float = 1.0
        port: str = ""
        names: tuple[str, ...] = ()

    p = parse_params(P, {"rate_hz": 5, "names": ["a", "b"]}, "f: services.x.y")
    assert p.rate_hz == 5 and p.names == ("a", "b")
    with pytest.raises(ConfigError, match=r"services.x.y.rate_hz: expected float, got str"):
        parse_params(P, {"rate_hz": "fast"}, "f: services.x.y")
    with pytest.raises(ConfigError, match="unknown parameter"):
        parse_params(P, {"speed": 1}, "f: services.x.y")


def test_sim_clock_releases_sleepers_in_order():
    async def go() -> list[float]:
        clock = Clock("sim")
        woke: list[float] = []

        async def sleeper(t: float) -> None:
            await clock.sleep_until(t)
            woke.append(clock.now())

        tasks = [asyncio.ensure_future(sleeper(t)) for t in (0.3, 0.1)]
        await asyncio.sleep(0)
        for t in (0.05, 0.1, 0.2, 0.3):
            clock.advance(t)
            await asyncio.sleep(0)
        await asyncio.gather(*tasks)
        return woke

    assert asyncio.run(go()) == [0.1, 0.3]


def test_rate_meter():
    meter = RateMeter()
    for i in range(101):
        meter.tick(i * 0.01)
    assert meter.rate(1.0) == pytest.approx(100.0, rel=0.02)
    assert meter.rate(100.0) == 0.0
    steady = RateMeter()
    for i in range(2000):  # 100 Hz for 20 s, then 10 Hz for 10 s: the rate of the last few seconds
        steady.tick(i * 0.01)
    assert steady.rate(20.0) == pytest.approx(100.0, rel=0.03)
    for i in range(100):
        steady.tick(20.0 + i * 0.1)
    assert steady.rate(30.0) == pytest.approx(10.0, rel=0.05)


def test_rate_meter_ticked_and_read_from_several_threads_keeps_count():
    meter = RateMeter()
    errors: list[BaseException] = []

    def tick(offset: float) -> None:
        try:
            for i in range(20_000):
                meter.tick(offset + i * 1e-3)
        except BaseException as exc:  # noqa: BLE001 - reported by the assertion below
            errors.append(exc)

    def read() -> None:
        try:
            for i in range(20_000):
                meter.rate(i * 1e-3 + 10.0)  # trims the window the tickers append to
        except BaseException as exc:  # noqa: BLE001
            errors.append(exc)

    threads = [threading.Thread(target=tick, args=(k * 0.5,)) for k in range(3)] + [threading.Thread(target=read)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    assert meter.count == 60_000
