"""The wiring: port declarations + deployments -> keys and edges; every subscription has a publisher."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import pytest

from deploy import graph as graph_module
from deploy.graph import main as graph_main
from deploy.supervisor import up_main
from shared import keys
from shared.config import ConfigError, load_deployment
from shared.ports import declared_services, ports_of
from shared.wiring import bind, edges, published, start_order

ROOT = Path(__file__).resolve().parents[2]
DEPLOYMENTS = sorted((ROOT / "deploy").glob("*.toml"))


@pytest.mark.parametrize("path", DEPLOYMENTS, ids=lambda p: p.name)
def test_every_subscription_of_every_deployment_has_a_publisher(path):
    dep = load_deployment(path)
    graph, problems = edges(dep)
    assert not problems, "\n".join(problems)
    wired = {(e.consumer, e.input) for e in graph}
    for service, instance in dep.instances():  # every declared input is an edge or disconnected on purpose
        for port, inp in bind(dep, service, instance).inputs.items():
            assert (f"{service}/{instance}", port) in wired or not inp.sources, f"{service}/{instance}.{port}"


def _sim_text() -> str:
    text = (ROOT / "deploy/sim.toml").read_text()
    assert "[services.recon.main]" in text
    return text


def test_a_renamed_instance_connects_through_the_deployments_remap(tmp_path):
    renamed = _sim_text().replace("[services.recon.main]", "[services.recon.left]")
    broken = tmp_path / "broken.toml"
    broken.write_text(renamed)
    _, problems = edges(load_deployment(broken))
    assert sorted(p.split(" ")[0] for p in problems) == ["camhub/main.scene", "panel/main.scene",
                                                             "panel/main.tactile_mesh", "policy/main.scene"]

    fixed = tmp_path / "fixed.toml"
    remapped = renamed.replace("[services.policy.main]", '[services.policy.main]\ninputs = { scene = "recon/left" }')
    remapped = remapped.replace("[services.camhub.main]", '[services.camhub.main]\ninputs = { scene = "recon/left" }')
    fixed.write_text(remapped.replace("[services.panel.main]",
                                      '[services.panel.main]\ninputs = { scene = "recon/left/scene", '
                                      'tactile_mesh = "recon/left/tactile_mesh" }'))
    dep = load_deployment(fixed)
    graph, problems = edges(dep)
    assert not problems
    assert {(e.producer, e.consumer) for e in graph if e.input == "scene"} == {("recon/left", "policy/main"),
                                                                               ("recon/left", "panel/main"),
                                                                               ("recon/left", "camhub/main")}
    assert bind(dep, "policy", "main").input("scene").key_exprs == ("xm/recon/left/scene",)
    assert "inputs" not in dep.params("policy", "main")  # a remap, not a service parameter


def test_a_list_remap_subscribes_each_producer_and_the_robot_model_picks_the_state_key(tmp_path):
    path = tmp_path / "d.toml"
    path.write_text(_sim_text().replace("[services.recon.main]",
                                        '[services.recon.main]\ninputs = { tactile = ["glove/left", "glove/right"] }'))
    tactile = bind(load_deployment(path), "recon", "main").input("tactile")
    assert tactile.key_exprs == ("xm/glove/left/tactile", "xm/glove/right/tactile")
    hand_arm = load_deployment(ROOT / "deploy/hand_arm.toml")
    assert bind(hand_arm, "trajopt", "main").input("state").key_exprs == ("xm/robot/hand_arm/state",)
    assert bind(hand_arm, "robot", "hand_arm").output("state").keys == {"": "xm/robot/hand_arm/state"}


@pytest.mark.parametrize("remap, error", [
    ('inputs = { scenery = "recon/main" }', "has no input scenery"),
    ('inputs = { scene = "world/sim/truth" }', "publishes xm_msgs/msg/GroundTruth, the input reads xm_msgs/msg/Scene"),
    ('inputs = { scene = "recon/main/nothing" }', "recon has no output 'nothing'"),
    ('inputs = { scene = "teleporter/main" }', "unknown service 'teleporter'"),
    ('inputs = { scene = "recon" }', "expected \"service/instance\""),
])
def test_bad_remaps_are_named(tmp_path, remap, error):
    path = tmp_path / "d.toml"
    path.write_text(_sim_text().replace("[services.policy.main]", f"[services.policy.main]\n{remap}"))
    with pytest.raises(ConfigError, match=re.escape(error)):
        bind(load_deployment(path), "policy", "main")


def test_the_registry_is_the_reference_deployments_declared_outputs():
    sim = load_deployment(ROOT / "deploy/sim.toml")
    assert {s.key for s in keys.REGISTRY} == {s.key for s in published(sim)}
    for spec in keys.REGISTRY:
        out = ports_of(spec.service).output(spec.port)
        assert (spec.msgtype, spec.rate_hz) == (out.msgtype, out.rate_hz)
    assert "xm/glove/left/raw" not in keys.BY_KEY  # off unless the deployment sets publish_raw
    assert keys.OPTIONAL == {"xm/glove/*/raw": "xm_msgs/msg/TactileRaw", "xm/glove/*/imu": "xm_msgs/msg/Imu"}


def test_key_matching_follows_zenoh_chunks():
    assert keys.key_matches("xm/**", "xm/glove/left/tactile")
    assert keys.key_matches("xm/*/left/*", "xm/glove/left/tactile")
    assert not keys.key_matches("xm/*/tactile", "xm/glove/left/tactile")  # `*` is one chunk, never a `/`
    assert keys.key_matches("xm/**/tactile", "xm/glove/left/tactile")
    assert not keys.key_matches("xm/camhub/*/image", "xm/camhub/cam0/info")
    assert keys.msgtype_of("xm/glove/left/raw") == "xm_msgs/msg/TactileRaw"
    assert keys.msgtype_of("xm/glove/left/extra/raw") is None  # fnmatch's `*` would have crossed the `/`
    assert keys.msgtype_of("xm/robot/hand_arm/state") == "sensor_msgs/msg/JointState"
    with pytest.raises(ValueError, match="not a Zenoh key expression"):
        keys.key_matches("xm//bad", "xm/clock")


def test_services_are_the_packages_that_declare_ports_and_hosts_start_first():
    packages = {p.parent.name for p in (ROOT / "services").glob("*/__main__.py")}
    assert set(declared_services()) == packages
    order = start_order(load_deployment(ROOT / "deploy/sim.toml"))
    assert order[0] == ("world", "sim") and len(order) == len(set(order))


def test_xm_graph_prints_every_edge_and_fails_on_a_missing_publisher(tmp_path, capsys):
    out = tmp_path / "sim.svg"
    assert graph_main([str(ROOT / "deploy/sim.toml"), "--svg", str(out)]) == 0
    printed = capsys.readouterr()
    assert re.search(r"recon/main/scene\s+policy/main/scene\s+xm_msgs/msg/Scene\s+5 Hz\s+latest\(1\)", printed.out)
    assert re.search(r"world/sim/clock\s+every instance", printed.out)
    if shutil.which("dot"):
        assert out.read_text().lstrip().startswith("<?xml") and "policy/main" in out.read_text()
    broken = tmp_path / "broken.toml"
    broken.write_text(_sim_text().replace("[services.recon.main]", "[services.recon.left]"))
    assert graph_main([str(broken), "--no-svg"]) == 1
    assert "no instance of this deployment publishes it" in capsys.readouterr().out


def test_xm_graph_without_graphviz_writes_the_dot_file_and_says_how_to_render_it(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(graph_module.shutil, "which", lambda _name: None)
    out = tmp_path / "sim.svg"
    assert graph_main([str(ROOT / "deploy/sim.toml"), "--svg", str(out)]) == 0
    assert "apt-get install graphviz" in capsys.readouterr().err
    assert not out.exists() and '"recon/main" -> "policy/main"' in out.with_suffix(".dot").read_text()


def test_xm_up_refuses_a_bad_remap_before_starting_anything(tmp_path, capsys):
    path = tmp_path / "d.toml"
    remap = '[services.policy.main]\ninputs = { scene = "world/sim" }'
    path.write_text(_sim_text().replace("[services.policy.main]", remap))
    assert up_main([str(path), "--duration", "1"]) == 2
    assert "policy.main.inputs.scene: source 'world/sim': world has no output 'scene'" in capsys.readouterr().err
