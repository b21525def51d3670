"""Typed ports: what each service reads and writes, declared once in ``services/<name>/ports.py``.

A service package declares ``PORTS = Ports(...)``: its outputs (key, message type, nominal rate)
and its inputs (the producer's output each one reads by default, message type, queue policy).
The deployment may remap an input to another producer instance::

    [services.policy.main]
    inputs = { scene = "recon/left" }          # port -> "service/instance" or "service/instance/port"

``shared/wiring.py`` resolves declarations and deployment into keys and edges; ``xm graph`` draws
them. A folder ``services/<name>`` with a ``ports.py`` is a service; nothing else lists them.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path

SERVICES_DIR = Path(__file__).resolve().parent.parent / "services"
DEFAULT_KEY = "xm/{service}/{instance}/{port}"

# Instance names the workcell fans out over: one glove service instance per hand, one camhub key
# chunk per camera.
GLOVES = ("left", "right")
CAMERAS = tuple(f"cam{i}" for i in range(7))


@dataclass(frozen=True)
class QueuePolicy:
    kind: str  # "latest": keep the newest `depth` samples; "fifo": keep all up to `depth`, count overflow
    depth: int

    def __str__(self) -> str:
        return f"latest({self.depth})" if self.kind == "latest" else f"fifo({self.depth})"


def latest(depth: int = 1) -> QueuePolicy:
    return QueuePolicy("latest", depth)


def fifo(depth: int = 100_000) -> QueuePolicy:
    return QueuePolicy("fifo", depth)


@dataclass(frozen=True)
class Output:
    """One published stream. ``key`` is a template: ``{service}``, ``{instance}``, ``{port}`` and,
    for a port fanned out over ``each`` (one key per camera), ``{each}``."""

    port: str
    msgtype: str
    rate_hz: float  # nominal, in the simulated deployment
    doc: str
    key: str = DEFAULT_KEY
    each: tuple[str, ...] = ()
    on_change: bool = False  # also published whenever the value changes: rate_hz is a minimum
    enabled_by: str | None = None  # a bool parameter that turns it on (off unless the deployment sets it)

    def key_for(self, service: str, instance: str, each: str = "*") -> str:
        return self.key.format(service=service, instance=instance, port=self.port, each=each)


@dataclass(frozen=True)
class Input:
    """One subscription. ``source`` names the producer's output: ``service/instance/port``
    (``*`` as instance: every instance), or several of them; ``only`` picks one key of a fanned-out
    output (one camera). ``{robot}`` in a source is the deployment's robot model."""

    port: str
    source: str | tuple[str, ...]
    msgtype: str
    queue: QueuePolicy = field(default_factory=latest)
    doc: str = ""
    only: str | None = None
    when: tuple[str, str] | None = None  # (parameter, value): subscribed only where the deployment sets it so

    def enabled(self, params: dict) -> bool:
        return self.when is None or params.get(self.when[0]) == self.when[1]

    @property
    def sources(self) -> tuple[str, ...]:
        return (self.source,) if isinstance(self.source, str) else tuple(self.source)


@dataclass(frozen=True)
class Ports:
    service: str
    doc: str
    outputs: tuple[Output, ...] = ()
    inputs: tuple[Input, ...] = ()
    hosts_devices: bool = False  # creates devices other services open: the supervisor starts it first

    def output(self, port: str) -> Output:
        for out in self.outputs:
            if out.port == port:
                return out
        raise KeyError(f"{self.service} has no output {port!r} (outputs: {', '.join(self.output_names())})")

    def input(self, port: str) -> Input:
        for inp in self.inputs:
            if inp.port == port:
                return inp
        names = ", ".join(i.port for i in self.inputs) or "none"
        raise KeyError(f"{self.service} has no input {port!r} (inputs: {names})")

    def output_names(self) -> list[str]:
        return [o.port for o in self.outputs]


def declared_services() -> tuple[str, ...]:
    """Every ``services/<name>`` package that declares its ports, in name order."""
    return tuple(sorted(p.parent.name for p in SERVICES_DIR.glob("*/ports.py")))


@cache
def ports_of(service: str) -> Ports:
    """The declaration in ``services/<service>/ports.py`` (a light module: no heavy imports)."""
    if service not in declared_services():
        raise KeyError(f"unknown service {service!r} (known: {', '.join(declared_services())})")
    ports = importlib.import_module(f"services.{service}.ports").PORTS
    if not isinstance(ports, Ports) or ports.service != service:
        raise TypeError(f"services/{service}/ports.py: PORTS must be Ports(service={service!r}, ...)")
    return ports


def all_ports() -> dict[str, Ports]:
    return {name: ports_of(name) for name in declared_services()}
