"""Deployment files: which services run, where the router is, and each instance's parameters.

A deployment is TOML::

    [deployment]
    name = "sim"
    router = "tcp/127.0.0.1:7447"
    clock = "sim"                 # "sim": time from xm/clock; "wall": system time
    run_dir = "/tmp/xm-sim"       # ptys and sockets of simulated devices
    robot = "workcell"            # robot model: default of every service's `robot` parameter

    [services.glove.left]         # one table per service instance
    port = "{run_dir}/glove-left"

    [services.policy.main]
    inputs = { scene = "recon/main" }   # optional: remap an input port to another producer

A service is any ``services/<name>`` package with a ``ports.py`` (shared/ports.py). Parameters are
checked against the service's dataclass; errors name the file, key and type.
"""

from __future__ import annotations

import dataclasses
import tomllib
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

from shared.ports import declared_services

DEFAULT_ROBOT = "workcell"

T = TypeVar("T")


class ConfigError(ValueError):
    """A deployment file that cannot be used; the message says where and why."""


@dataclass(frozen=True)
class Deployment:
    path: Path
    name: str
    router: str
    clock: str
    run_dir: Path
    services: dict[str, dict[str, dict[str, Any]]] = field(default_factory=dict)  # name -> instance -> params
    robot: str = DEFAULT_ROBOT

    def instances(self) -> list[tuple[str, str]]:
        return [(name, inst) for name, insts in self.services.items() for inst in insts]

    def params(self, service: str, instance: str) -> dict[str, Any]:
        try:
            raw = self.services[service][instance]
        except KeyError:
            known = ", ".join(f"{s}/{i}" for s, i in self.instances()) or "none"
            raise ConfigError(f"{self.path}: no instance {service}/{instance} (deployment has: {known})") from None
        return {k: _expand(v, self.run_dir) for k, v in raw.items() if k != "inputs"}

    def inputs(self, service: str, instance: str) -> dict[str, str | list[str]]:
        """The instance's input remaps (``inputs = { port = "service/instance" }``), empty if none."""
        return dict(self.services.get(service, {}).get(instance, {}).get("inputs", {}))

    def service_params(self, cls: type[T], service: str, instance: str) -> T:
        """The instance's parameters as ``cls``; a ``robot`` field defaults to the deployment's robot."""
        raw = self.params(service, instance)
        if "robot" in {f.name for f in dataclasses.fields(cls)}:  # type: ignore[arg-type]
            raw.setdefault("robot", self.robot)
        return parse_params(cls, raw, f"{self.path}: services.{service}.{instance}")


def _expand(value: Any, run_dir: Path) -> Any:
    """``{run_dir}`` in string parameters (also inside lists) becomes the deployment's run_dir."""
    if isinstance(value, str):
        return value.replace("{run_dir}", str(run_dir))
    if isinstance(value, list):
        return [_expand(v, run_dir) for v in value]
    return value


def _expect(value: Any, kind: type, where: str) -> Any:
    if not isinstance(value, kind) or (kind is not bool and isinstance(value, bool) and kind is not object):
        raise ConfigError(f"{where}: expected {kind.__name__}, got {type(value).__name__} {value!r}")
    return value


def load_deployment(path: str | Path) -> Deployment:
    path = Path(path)
    if not path.exists():
        raise ConfigError(f"{path}: deployment file not found (try deploy/sim.toml)")
    try:
        data = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None
    head = data.get("deployment")
    if not isinstance(head, dict):
        raise ConfigError(f"{path}: missing [deployment] table")
    name = _expect(head.get("name", path.stem), str, f"{path}: deployment.name")
    router = _expect(head.get("router", "tcp/127.0.0.1:7447"), str, f"{path}: deployment.router")
    clock = _expect(head.get("clock", "wall"), str, f"{path}: deployment.clock")
    if clock not in ("wall", "sim"):
        raise ConfigError(f"{path}: deployment.clock: expected \"wall\" or \"sim\", got {clock!r}")
    run_dir = Path(_expect(head.get("run_dir", f"/tmp/xm-{name}"), str, f"{path}: deployment.run_dir"))
    robot = _expect(head.get("robot", DEFAULT_ROBOT), str, f"{path}: deployment.robot")
    services_raw = data.get("services", {})
    _expect(services_raw, dict, f"{path}: services")
    known = declared_services()
    services: dict[str, dict[str, dict[str, Any]]] = {}
    for svc, insts in services_raw.items():
        if svc not in known:
            raise ConfigError(f"{path}: services.{svc}: unknown service (known: {', '.join(known)}; "
                              "a service is a services/<name> package with a ports.py)")
        _expect(insts, dict, f"{path}: services.{svc}")
        for inst, params in insts.items():
            _expect(params, dict, f"{path}: services.{svc}.{inst}")
            _check_remaps(params.get("inputs", {}), f"{path}: services.{svc}.{inst}.inputs")
        services[svc] = insts
    return Deployment(path, name, router, clock, run_dir, services, robot)


def _check_remaps(remaps: Any, where: str) -> None:
    _expect(remaps, dict, where)
    for port, source in remaps.items():
        sources = source if isinstance(source, list) else [source]
        for s in sources:
            if not isinstance(s, str) or not 2 <= len(s.split("/")) <= 3 or "" in s.split("/"):
                raise ConfigError(f"{where}.{port}: expected \"service/instance\" or \"service/instance/port\" "
                                  f"(or a list of them), got {source!r}")


def _type_ok(value: Any, hint: Any) -> bool:
    origin = typing.get_origin(hint)
    if hint is Any:
        return True
    if origin in (typing.Union, types.UnionType):
        return any(_type_ok(value, h) for h in typing.get_args(hint))
    if hint is type(None):
        return value is None
    if hint is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if hint is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if origin in (list, tuple):
        args = typing.get_args(hint)
        return isinstance(value, list) and (not args or all(_type_ok(v, args[0]) for v in value))
    if origin is dict:
        return isinstance(value, dict)
    return isinstance(value, hint)


def parse_params(cls: type[T], params: dict[str, Any], where: str) -> T:
    """Build a parameter dataclass from a TOML table, rejecting unknown keys and wrong types."""
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    for key, value in params.items():
        if key not in names:
            raise ConfigError(f"{where}.{key}: unknown parameter (known: {', '.join(sorted(names))})")
        if not _type_ok(value, hints[key]):
            want = getattr(hints[key], "__name__", str(hints[key]))
            raise ConfigError(f"{where}.{key}: expected {want}, got {type(value).__name__} {value!r}")
    values = {k: (tuple(v) if isinstance(v, list) and typing.get_origin(hints[k]) is tuple else v)
              for k, v in params.items()}
    return cls(**values)
