"""A deployment on two hosts: two network namespaces joined by a veth pair on this machine
(deploy/netns.py, root only). The gloves, cameras, world and robot run on one, recorder, policy and
trajopt on the other; the routers link over mutual TLS with certificates from `xm certs`. The
recording made on the second host holds the first host's streams, nothing dropped; a client
without a certificate, one with a certificate of another CA, and puts on keys the peer host may
not publish are refused every time."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from mcap.reader import make_reader

from deploy import certs, netns
from tests.conftest import write_deployment

ROOT = Path(__file__).resolve().parents[2]
PROBE = str(ROOT / "tests/integration/_multihost_probe.py")
ROUTER = "tcp/127.0.0.1:7447"  # each namespace has a loopback of its own
A_SERVICES = ["world/sim", "glove/left", "glove/right", "camhub/main", "robot/workcell"]
B_SERVICES = ["recorder/main", "policy/main", "trajopt/main"]

pytestmark = pytest.mark.skipif(netns.available() is not None, reason=str(netns.available()))


def probe(ns: str, *args: str, timeout: float = 180) -> dict:
    r = subprocess.run(["ip", "netns", "exec", ns, sys.executable, PROBE, *map(str, args)], capture_output=True,
                       text=True, timeout=timeout, cwd=ROOT)
    assert r.returncode == 0, r.stderr[-2000:]
    return json.loads(r.stdout.strip().splitlines()[-1])


def deployment(tmp: Path, addresses: tuple[str, str]) -> Path:
    base = tmp / "base.toml"
    write_deployment(base, ROUTER, {
        "world": {"sim": {"glove_ports": ["{run_dir}/glove-left", "{run_dir}/glove-right"],
                          "robot_port": "{run_dir}/robot-board", "glove_rate_hz": 100.0}},
        "glove": {"left": {"port": "{run_dir}/glove-left"}, "right": {"port": "{run_dir}/glove-right"}},
        "camhub": {"main": {"source": "sim", "rate_hz": 5.0, "width": 128, "height": 96}},
        "robot": {"workcell": {"port": "{run_dir}/robot-board"}},
        "recorder": {"main": {"directory": str(tmp / "recordings")}},
        "policy": {"main": {"method": "naive"}},
        "trajopt": {"main": {}},
    }, clock="sim")
    text = base.read_text() + f"""
[tls]
dir = "{tmp / 'certs'}"

[hosts.cameras]
address = "{addresses[0]}"
services = {json.dumps(A_SERVICES)}

[hosts.learner]
address = "{addresses[1]}"
services = {json.dumps(B_SERVICES)}
"""
    path = tmp / "two_hosts.toml"
    path.write_text(text)
    return path


def test_two_hosts_record_across_tls_and_refuse_what_the_acl_forbids(tmp_path):
    names = (f"xma{os.getpid() % 10000}", f"xmb{os.getpid() % 10000}")
    pair = netns.up(*names, subnet=os.getpid() % 200)
    procs = []
    try:
        dep = deployment(tmp_path, pair.addresses)
        assert certs.main([str(dep)]) == 0
        for ns, host in zip(names, ("cameras", "learner"), strict=True):
            log = (tmp_path / f"{host}.log").open("w")
            procs.append(netns.run(ns, [sys.executable, "-m", "shared.cli", "up", str(dep), "--host", host,
                                        "--quiet", "--no-standby"], cwd=ROOT, stdout=log, stderr=subprocess.STDOUT,
                                   start_new_session=True))
        a, b = names
        link_a = f"tls/{pair.addresses[0]}:7448"
        # The learner's recorder records the cameras host's streams for 10 s.
        assert probe(b, "health", ROUTER, "xm/glove/left/@health", 180)["ok"], (tmp_path / "cameras.log").read_text()
        keys = ("xm/glove/left/tactile", "xm/glove/right/tactile", "xm/camhub/cam0/image", "xm/clock",
                "xm/robot/workcell/state")
        flowing = probe(b, "flowing", ROUTER, 180, *keys)
        assert flowing["ok"], flowing
        rec = probe(b, "record", ROUTER, 10, tmp_path / "recordings" / "two_hosts.mcap")
        assert rec["stop"] and rec["stop"][0]["ok"], rec
        counts = rec["stop"][0]["messages"]
        for key in keys:
            assert counts.get(key, 0) > 0, f"{key} did not reach the other host: {sorted(counts)}"
        assert not rec["health"][0].get("dropped"), rec["health"][0]
        with open(rec["stop"][0]["path"], "rb") as f:  # a stock reader reads it
            topics = {ch.topic for ch in make_reader(f).get_summary().channels.values()}
        assert "xm/glove/left/tactile" in topics
        # The learner may publish its own services' keys to the cameras host, not the gloves' or the clock.
        listener = subprocess.Popen(["ip", "netns", "exec", a, sys.executable, PROBE, "listen", ROUTER, "xm/**", "8"],
                                    stdout=subprocess.PIPE, text=True, cwd=ROOT)
        sent = probe(b, "publish", ROUTER, 5, "xm/trajopt/main/probe", "xm/glove/left/probe")
        heard = json.loads(listener.communicate(timeout=60)[0].strip().splitlines()[-1])
        assert sent["sent_per_key"] > 10
        assert heard.get("xm/trajopt/main/probe", 0) > 0
        assert heard.get("xm/glove/left/probe", 0) == 0, "the ACL let a glove key through"
        # No certificate, or one of another CA: refused.
        nocert = probe(b, "connect", link_a, tmp_path / "certs" / "ca.pem")
        assert not nocert["connected"], nocert
        other = tmp_path / "other"
        ca, key = certs.make_ca(other)
        certs.make_host_cert(other, "learner", [pair.addresses[1]], ca, key)
        foreign = probe(b, "connect", link_a, tmp_path / "certs" / "ca.pem", other / "learner.pem",
                        other / "learner.key")
        assert not foreign["connected"], foreign
        valid = probe(b, "connect", link_a, tmp_path / "certs" / "ca.pem", tmp_path / "certs" / "learner.pem",
                      tmp_path / "certs" / "learner.key")
        assert valid["connected"], valid
    finally:
        netns.stop(procs)
        netns.down(*names)
