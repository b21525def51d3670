"""Opening Zenoh sessions with the project's rules: explicit endpoints, no multicast scouting."""

from __future__ import annotations

import json
import socket
from collections.abc import Callable
from typing import Any

import zenoh
import zenoh.ext

TX_QUEUE_BATCHES = 16  # per link, for the data priority (Zenoh's maximum; its default is 2)
DROP_AFTER_US = 10_000  # a sample waits this long for room in a full queue before it is dropped


class EndpointError(RuntimeError):
    """The router endpoint is unusable (bad syntax or the port is taken)."""


def _config(mode: str, listen: list[str] | None = None, connect: list[str] | None = None,
            extra: dict | None = None) -> zenoh.Config:
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("scouting/gossip/enabled", "false" if mode == "client" else "true")
    # Shared memory between the processes of one host, for the payloads a typed publisher puts from
    # its pool (shared/runtime/shm.py). Zenoh's implicit pool (every session copying each message
    # over 3 kB into a 16 MB pool of its own) stays off: a receiver keeps every pool it read from
    # mapped, also after its publisher restarted, so only large-payload publishers get a pool.
    conf.insert_json5("transport/shared_memory/enabled", "true")
    conf.insert_json5("transport/shared_memory/transport_optimization/enabled", "false")
    # Room on each link for a CPU-starved reader: Zenoh's default (2 batches of 64 kB per priority,
    # a full queue dropping after 1 ms) lost 7 % of recon's 62 kB tactile meshes on the router's
    # link to the recorder in the chaos soak, uncounted; 16 batches and 10 ms lost none in the next
    # hour (docs/architecture.md). A full queue still drops rather than stall a publisher for long.
    conf.insert_json5("transport/link/tx/queue/size/data", str(TX_QUEUE_BATCHES))
    conf.insert_json5("transport/link/tx/queue/congestion_control/drop/wait_before_drop", str(DROP_AFTER_US))
    conf.insert_json5("listen/endpoints", json.dumps(listen or []))
    conf.insert_json5("connect/endpoints", json.dumps(connect or []))
    for path, value in (extra or {}).items():  # e.g. a host's TLS links and access control (deploy/hosts.py)
        conf.insert_json5(path, json.dumps(value))
    return conf


def parse_tcp(endpoint: str) -> tuple[str, int]:
    if not endpoint.startswith("tcp/") or ":" not in endpoint:
        raise EndpointError(f"endpoint {endpoint!r}: expected tcp/<host>:<port>, e.g. tcp/127.0.0.1:7447")
    host, _, port = endpoint[4:].rpartition(":")
    try:
        return host.strip("[]"), int(port)
    except ValueError:
        raise EndpointError(f"endpoint {endpoint!r}: port {port!r} is not a number") from None


def check_port_free(endpoint: str) -> None:
    host, port = parse_tcp(endpoint)
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as the router does: TIME_WAIT is fine
        try:
            sock.bind((host, port))
        except OSError as exc:
            raise EndpointError(
                f"cannot listen on {endpoint}: {exc.strerror} (another workcell or zenohd is running? "
                f"stop it, or set [deployment] router to a free port)") from None


def open_router(endpoint: str, extra: dict | None = None) -> zenoh.Session:
    """A router listening on ``endpoint``; ``extra``: further configuration entries (path -> value)."""
    check_port_free(endpoint)
    return zenoh.open(_config("router", listen=[endpoint], extra=extra))


def open_client(endpoint: str) -> zenoh.Session:
    parse_tcp(endpoint)
    return zenoh.open(_config("client", connect=[endpoint]))


def declare_publisher(session: zenoh.Session, key: str, congestion: zenoh.CongestionControl,
                      cache_last: bool = False) -> Any:
    """A publisher on ``key``; with ``cache_last`` its latest sample stays with it, for subscribers
    that ask for history when they start (a state such as the session label reaches a recorder that
    starts between two of its messages). Zenoh's cache needs its samples ordered: by sequence numbers
    here (miss detection), which leaves the session's own timestamping off."""
    if not cache_last:
        return session.declare_publisher(key, congestion_control=congestion)
    return zenoh.ext.declare_advanced_publisher(session, key, congestion_control=congestion,
                                                cache=zenoh.ext.CacheConfig(max_samples=1),
                                                sample_miss_detection=zenoh.ext.MissDetectionConfig())


def declare_subscriber(session: zenoh.Session, key_expr: str, callback: Callable[[zenoh.Sample], None],
                       history: bool = False) -> Any:
    """A subscriber on ``key_expr``; with ``history`` it first gets the latest sample each matching
    ``cache_last`` publisher holds, then the live ones."""
    if not history:
        return session.declare_subscriber(key_expr, callback)
    return zenoh.ext.declare_advanced_subscriber(session, key_expr, callback,
                                                 history=zenoh.ext.HistoryConfig(max_samples=1))
