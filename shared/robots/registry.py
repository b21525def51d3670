"""The registry of robot descriptions: ``describe(name)`` for every robot model the software runs.
Add a robot: docs/architecture.md."""

from __future__ import annotations

from shared.robots import hand_arm, workcell
from shared.robots.description import DerivedPoint, GraspRoles, RobotDescription

REGISTRY: dict[str, RobotDescription] = {d.name: d for d in (workcell.DESCRIPTION, hand_arm.DESCRIPTION)}
DEFAULT_ROBOT = workcell.DESCRIPTION.name  # what a deployment runs unless it names another robot

__all__ = ["DEFAULT_ROBOT", "REGISTRY", "DerivedPoint", "GraspRoles", "RobotDescription", "UnknownRobotError",
           "describe", "derived_points", "joints_with"]


class UnknownRobotError(ValueError):
    """No description of that robot model."""


def describe(name: str) -> RobotDescription:
    try:
        return REGISTRY[name]
    except KeyError:
        raise UnknownRobotError(f"no robot model {name!r} (known: {', '.join(REGISTRY)})") from None


def joints_with(attribute: str) -> frozenset[str]:
    """Joint names any registered robot lists in ``attribute`` (e.g. "pneumatic_joints"): for code
    that sees joint names only, such as the simulated control board."""
    return frozenset(j for d in REGISTRY.values() for j in getattr(d, attribute))


def derived_points() -> dict[str, DerivedPoint]:
    """Every registered robot's derived plan points by name."""
    return {p.name: p for d in REGISTRY.values() for p in d.derived_points}
