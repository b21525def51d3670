"""The key registry: every key of the workcell, its message type, publisher and nominal rate.

Derived from the services' port declarations (services/*/ports.py), so the declarations are the
one place keys are written down. ``REGISTRY`` holds the concrete keys deploy/sim.toml publishes
(contract tests, the recorder and the integration test read it; rates are the simulated
deployment's); ``PATTERNS`` holds every declared output over any instance, so any deployment's
keys are typed. A service publishing a key that is not declared is a bug.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import zenoh

from shared.config import load_deployment
from shared.ports import CAMERAS, GLOVES, all_ports
from shared.wiring import KeySpec, intersects, published

__all__ = ["BY_KEY", "CAMERAS", "GLOVES", "OPTIONAL", "PATTERNS", "REGISTRY", "KeySpec", "key_matches",
           "matching", "msgtype_of", "robot_state_key", "service_key"]

REFERENCE_DEPLOYMENT = Path(__file__).resolve().parent.parent / "deploy" / "sim.toml"


def _patterns() -> tuple[KeySpec, ...]:
    return tuple(KeySpec(out.key_for(name, "*"), out.msgtype, name, out.rate_hz, out.doc, out.on_change,
                         "*", out.port)
                 for name, ports in all_ports().items() for out in ports.outputs)


REGISTRY: tuple[KeySpec, ...] = tuple(published(load_deployment(REFERENCE_DEPLOYMENT)))
BY_KEY: dict[str, KeySpec] = {spec.key: spec for spec in REGISTRY}
PATTERNS: tuple[KeySpec, ...] = _patterns()

# Outputs published only when a parameter enables them, typed here so the recorder can store them.
OPTIONAL: dict[str, str] = {
    out.key_for(name, "*"): out.msgtype
    for name, ports in all_ports().items() for out in ports.outputs if out.enabled_by is not None
}


def service_key(service: str, instance: str, topic: str) -> str:
    return f"xm/{service}/{instance}/{topic}"


def robot_state_key(robot: str) -> str:
    """Where the measured state of robot model ``robot`` is published: the robot service's instance
    carries the model's name (``[services.robot.<robot>]``), so trajopt and panel find it from theirs."""
    return service_key("robot", robot, "state")


@lru_cache(maxsize=4096)
def is_internal(key: str) -> bool:
    """Health, liveliness and command keys (a chunk starting with ``@``): never recorded or bridged."""
    return any(chunk.startswith("@") for chunk in key.split("/"))


def msgtype_of(key: str) -> str | None:
    """Message type of a concrete key, or None when no service declares it."""
    spec = BY_KEY.get(key)
    if spec is not None:
        return spec.msgtype
    try:
        expr = zenoh.KeyExpr(key)
    except zenoh.ZError:
        return None
    for pattern in PATTERNS:
        if zenoh.KeyExpr(pattern.key).includes(expr):
            return pattern.msgtype
    return None


def matching(pattern: str) -> list[KeySpec]:
    """Registered keys matching a Zenoh key expression (`*` one chunk, `**` any chunks)."""
    return [spec for spec in REGISTRY if key_matches(pattern, spec.key)]


def key_matches(pattern: str, key: str) -> bool:
    """Whether key expression ``pattern`` matches ``key``, by Zenoh's rules; invalid: ValueError."""
    try:
        return intersects(pattern, key)
    except zenoh.ZError as exc:
        raise ValueError(f"not a Zenoh key expression: {pattern!r} or {key!r} ({exc})") from None
