"""Deployments across hosts: which host runs which services, and each host's router.

A deployment may place its services on hosts::

    [tls]
    dir = "certs"          # `xm certs` writes here (relative to the deployment file)
    link_port = 7448       # routers link over TLS on this port of each host's address

    [hosts.cameras]
    address = "10.0.0.1"
    services = ["world/sim", "glove/left", "glove/right", "camhub/main", "robot/workcell"]

    [hosts.learner]
    address = "10.0.0.2"
    services = ["recorder/main", "policy/main", "trajopt/main"]

``xm up deploy/X.toml --host cameras`` runs that host's router and its services. Services reach
their own host's router on the deployment's ``router`` endpoint (loopback); the routers link over
TLS with certificates on both sides (deploy/certs.py). Each router refuses what a peer host may
not send: the keys of services placed on other hosts (a learner cannot publish glove data or the
clock); the peer is known by its certificate's common name. Pure: builds configuration, no I/O
besides reading the deployment file.
"""

from __future__ import annotations

import ipaddress
import tomllib
from dataclasses import dataclass
from pathlib import Path

from shared.config import Deployment
from shared.wiring import published

DEFAULT_LINK_PORT = 7448


class HostError(ValueError):
    """A host placement that cannot be used; the message says what and how to fix it."""


@dataclass(frozen=True)
class Host:
    name: str
    address: str
    services: tuple[tuple[str, str], ...]  # (service, instance)


@dataclass(frozen=True)
class Hosts:
    hosts: dict[str, Host]
    tls_dir: Path
    link_port: int

    def host(self, name: str) -> Host:
        if name not in self.hosts:
            raise HostError(f"no host {name!r} in this deployment (hosts: {', '.join(self.hosts) or 'none'})")
        return self.hosts[name]

    def link(self, host: Host) -> str:
        address = f"[{host.address}]" if ":" in host.address else host.address
        return f"tls/{address}:{self.link_port}"


def load_hosts(deployment: Deployment) -> Hosts:
    """The deployment's ``[hosts.*]`` and ``[tls]`` tables, checked: every instance on exactly one host."""
    raw = tomllib.loads(Path(deployment.path).read_text())
    where = str(deployment.path)
    tls = raw.get("tls", {})
    tls_dir = Path(deployment.path).parent / tls.get("dir", "certs")
    link_port = tls.get("link_port", DEFAULT_LINK_PORT)
    if not isinstance(link_port, int) or not 0 < link_port < 65536:
        raise HostError(f"{where}: tls.link_port must be a port number, got {link_port!r}")
    instances = set(deployment.instances())
    placed: dict[tuple[str, str], str] = {}
    hosts = {}
    for name, table in raw.get("hosts", {}).items():
        address = table.get("address")
        try:
            ipaddress.ip_address(address)
        except (TypeError, ValueError):
            raise HostError(f"{where}: hosts.{name}.address must be an IP address, got {address!r}") from None
        services = []
        for entry in table.get("services", []):
            svc, _, inst = str(entry).partition("/")
            if (svc, inst) not in instances:
                have = ", ".join(f"{s}/{i}" for s, i in sorted(instances))
                raise HostError(f"{where}: hosts.{name}.services: {entry!r} is no service instance of this "
                                f"deployment (it has: {have})")
            if (svc, inst) in placed:
                raise HostError(f"{where}: {entry} is placed on both {placed[(svc, inst)]} and {name}")
            placed[(svc, inst)] = name
            services.append((svc, inst))
        hosts[name] = Host(name, address, tuple(services))
    if hosts and (unplaced := sorted(instances - set(placed))):
        raise HostError(f"{where}: not placed on any host: {', '.join(f'{s}/{i}' for s, i in unplaced)} "
                        "(add them to a [hosts.*] services list)")
    return Hosts(hosts, tls_dir, link_port)


def forbidden_keys(deployment: Deployment, hosts: Hosts, peer: Host) -> list[str]:
    """Key expressions ``peer`` may not publish: every key of the services on the other hosts."""
    mine = set(peer.services)
    exprs = {f"xm/{s}/{i}/**" for host in hosts.hosts.values() if host is not peer for s, i in host.services}
    exprs |= {spec.key for spec in published(deployment) if (spec.service, spec.instance) not in mine}
    return sorted(exprs)


def router_config(deployment: Deployment, hosts: Hosts, name: str) -> dict:
    """Zenoh configuration entries (path -> value) for the router of host ``name``."""
    me = hosts.host(name)
    tls = hosts.tls_dir
    config: dict = {
        "listen/endpoints": [deployment.router, hosts.link(me)],
        "connect/endpoints": [hosts.link(h) for h in hosts.hosts.values() if h is not me],
        "connect/exit_on_failure": False,  # the other hosts may come up later
        "transport/link/tls/root_ca_certificate": str(tls / "ca.pem"),
        "transport/link/tls/listen_certificate": str(tls / f"{name}.pem"),
        "transport/link/tls/listen_private_key": str(tls / f"{name}.key"),
        "transport/link/tls/connect_certificate": str(tls / f"{name}.pem"),
        "transport/link/tls/connect_private_key": str(tls / f"{name}.key"),
        "transport/link/tls/enable_mtls": True,
    }
    rules, subjects, policies = [], [], []
    for peer in hosts.hosts.values():
        if peer is me:
            continue
        rules.append({"id": f"not-from-{peer.name}", "permission": "deny", "flows": ["ingress"],
                      "messages": ["put", "delete"], "key_exprs": forbidden_keys(deployment, hosts, peer)})
        subjects.append({"id": peer.name, "cert_common_names": [peer.name]})
        policies.append({"rules": [f"not-from-{peer.name}"], "subjects": [peer.name]})
    if rules:
        config["access_control"] = {"enabled": True, "default_permission": "allow", "rules": rules,
                                    "subjects": subjects, "policies": policies}
    return config
