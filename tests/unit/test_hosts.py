"""Multi-host placement (deploy/hosts.py) and certificates (deploy/certs.py): pure parts."""

from __future__ import annotations

import datetime as dt

import pytest

from deploy import certs
from deploy.hosts import HostError, forbidden_keys, load_hosts, router_config
from shared.config import load_deployment
from tests.conftest import write_deployment

SERVICES = {"world": {"sim": {}}, "glove": {"left": {"port": "{run_dir}/g"}}, "recorder": {"main": {}},
            "policy": {"main": {}}}


def deployment(tmp_path, hosts: str):
    path = write_deployment(tmp_path / "d.toml", "tcp/127.0.0.1:7447", SERVICES, clock="sim")
    path.write_text(path.read_text() + hosts)
    return load_deployment(path)


TWO = """
[hosts.cameras]
address = "10.0.0.1"
services = ["world/sim", "glove/left"]

[hosts.learner]
address = "10.0.0.2"
services = ["recorder/main", "policy/main"]
"""


def test_a_peer_may_not_publish_other_hosts_keys(tmp_path):
    dep = deployment(tmp_path, TWO)
    hosts = load_hosts(dep)
    learner = forbidden_keys(dep, hosts, hosts.host("learner"))
    assert "xm/glove/left/**" in learner and "xm/world/sim/**" in learner and "xm/clock" in learner
    assert not any(k.startswith(("xm/policy/", "xm/recorder/")) for k in learner)
    cameras = forbidden_keys(dep, hosts, hosts.host("cameras"))
    assert "xm/policy/main/**" in cameras and "xm/clock" not in cameras
    config = router_config(dep, hosts, "cameras")
    assert config["listen/endpoints"] == ["tcp/127.0.0.1:7447", "tls/10.0.0.1:7448"]
    assert config["connect/endpoints"] == ["tls/10.0.0.2:7448"]
    assert config["transport/link/tls/enable_mtls"] is True
    acl = config["access_control"]
    assert acl["subjects"] == [{"id": "learner", "cert_common_names": ["learner"]}]
    assert acl["rules"][0]["key_exprs"] == learner and acl["rules"][0]["permission"] == "deny"


@pytest.mark.parametrize("hosts, message", [
    (TWO.replace('"policy/main"', ""), "not placed on any host: policy/main"),
    (TWO.replace('"policy/main"', '"policy/main", "glove/left"'), "placed on both cameras and learner"),
    (TWO.replace('"recorder/main"', '"recorder/other"'), "no service instance"),
    (TWO.replace('"10.0.0.2"', '"learner.local"'), "must be an IP address"),
])
def test_bad_placements_say_what_to_fix(tmp_path, hosts, message):
    with pytest.raises(HostError, match=message):
        load_hosts(deployment(tmp_path, hosts))


def test_an_unknown_host_lists_the_hosts(tmp_path):
    hosts = load_hosts(deployment(tmp_path, TWO))
    with pytest.raises(HostError, match="hosts: cameras, learner"):
        hosts.host("robot")


def test_certificates_expired_or_from_another_ca_are_named(tmp_path):
    ca, key = certs.make_ca(tmp_path / "a")
    pem = certs.make_host_cert(tmp_path / "a", "cameras", ["10.0.0.1"], ca, key, days=30)
    assert certs.check_cert(pem, tmp_path / "a" / "ca.pem") is None
    later = dt.datetime.now(dt.UTC) + dt.timedelta(days=31)
    assert "expired" in certs.check_cert(pem, tmp_path / "a" / "ca.pem", now=later)
    certs.make_ca(tmp_path / "b")
    assert "not signed by the CA" in certs.check_cert(pem, tmp_path / "b" / "ca.pem")
    assert "cannot be read" in certs.check_cert(tmp_path / "missing.pem", tmp_path / "a" / "ca.pem")
