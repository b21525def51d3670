"""The dataflow of a deployment: port declarations (services/*/ports.py) + the deployment's
instances and input remaps -> concrete keys, subscriptions and edges.

``bind`` gives one instance the keys of its ports (the node subscribes and publishes through
it); ``published`` lists the keys a deployment publishes; ``edges`` and ``problems`` are what
``xm graph`` prints and what the wiring test asserts. Keys are matched with Zenoh's own key
expressions (``*`` one chunk, ``**`` any number).
"""

from __future__ import annotations

from dataclasses import dataclass

import zenoh

from shared.config import ConfigError, Deployment
from shared.ports import Input, Output, QueuePolicy, ports_of


@dataclass(frozen=True)
class KeySpec:
    key: str  # a concrete key (or, in keys.PATTERNS, a key expression over every instance)
    msgtype: str
    service: str
    rate_hz: float  # nominal rate in the simulated deployment
    description: str
    on_change: bool = False  # also published whenever the value changes: rate_hz is a minimum
    instance: str = "*"
    port: str = ""


@dataclass(frozen=True)
class Source:
    service: str
    instance: str  # or "*": every instance
    port: str

    def __str__(self) -> str:
        return f"{self.service}/{self.instance}/{self.port}"


@dataclass(frozen=True)
class BoundInput:
    port: str
    msgtype: str
    queue: QueuePolicy
    sources: tuple[Source, ...]
    key_exprs: tuple[str, ...]  # one subscription per source
    only: str | None = None


@dataclass(frozen=True)
class BoundOutput:
    port: str
    msgtype: str
    keys: dict[str, str]  # fan-out item (or "") -> key
    on_change: bool = False  # a state (also published when it changes): late subscribers may ask for its latest


@dataclass(frozen=True)
class Binding:
    """One instance's ports resolved to keys."""

    service: str
    instance: str
    inputs: dict[str, BoundInput]
    outputs: dict[str, BoundOutput]

    def input(self, port: str) -> BoundInput:
        if port not in self.inputs:
            raise KeyError(f"{self.service} declares no input {port!r} in services/{self.service}/ports.py "
                           f"(inputs: {', '.join(self.inputs) or 'none'})")
        return self.inputs[port]

    def output(self, port: str) -> BoundOutput:
        if port not in self.outputs:
            raise KeyError(f"{self.service} declares no output {port!r} in services/{self.service}/ports.py "
                           f"(outputs: {', '.join(self.outputs) or 'none'})")
        return self.outputs[port]


@dataclass(frozen=True)
class Edge:
    producer: str  # service/instance
    output: str
    consumer: str
    input: str
    msgtype: str
    rate_hz: float
    queue: QueuePolicy
    key: str  # the consumer's subscription
    only: str | None = None  # one key of a fanned-out output (one camera)


def _robot(deployment: Deployment, service: str, instance: str) -> str:
    robot = deployment.params(service, instance).get("robot", deployment.robot)
    return robot if isinstance(robot, str) else deployment.robot


def _resolve(inp: Input, remap: str | list[str] | None, robot: str, where: str) -> BoundInput:
    default_port = inp.sources[0].split("/")[2]
    texts = inp.sources if remap is None else ((remap,) if isinstance(remap, str) else tuple(remap))
    sources, exprs = [], []
    for text in texts:
        parts = text.format(robot=robot).split("/")
        if len(parts) == 2:
            parts.append(default_port)
        if len(parts) != 3 or "" in parts:
            raise ConfigError(f"{where}: source {text!r}: expected service/instance[/port]")
        source = Source(*parts)
        try:
            out = ports_of(source.service).output(source.port)
        except KeyError as exc:
            raise ConfigError(f"{where}: source {text!r}: {exc.args[0]}") from None
        if out.msgtype != inp.msgtype:
            raise ConfigError(f"{where}: source {source} publishes {out.msgtype}, the input reads {inp.msgtype}")
        if inp.only is not None and inp.only not in out.each:
            raise ConfigError(f"{where}: {inp.only!r} is not one of {source}'s keys ({', '.join(out.each)})")
        sources.append(source)
        exprs.append(out.key_for(source.service, source.instance, inp.only or "*"))
    return BoundInput(inp.port, inp.msgtype, inp.queue, tuple(sources), tuple(exprs), inp.only)


def _bound_output(out: Output, service: str, instance: str) -> BoundOutput:
    items = out.each or ("",)
    return BoundOutput(out.port, out.msgtype, {e: out.key_for(service, instance, e) for e in items}, out.on_change)


def bind(deployment: Deployment, service: str, instance: str) -> Binding:
    """Keys of one instance's ports, after the deployment's remaps (an input whose ``when`` the
    instance's parameters do not meet is left out); ConfigError names what is wrong."""
    ports = ports_of(service)
    where = f"{deployment.path}: services.{service}.{instance}.inputs"
    remaps = deployment.inputs(service, instance)
    unknown = sorted(set(remaps) - {i.port for i in ports.inputs})
    if unknown:
        raise ConfigError(f"{where}: {service} has no input {', '.join(unknown)} "
                          f"(inputs: {', '.join(i.port for i in ports.inputs) or 'none'})")
    robot = _robot(deployment, service, instance)
    params = deployment.params(service, instance)
    inputs = {i.port: _resolve(i, remaps.get(i.port), robot, f"{where}.{i.port}") for i in ports.inputs
              if i.enabled(params)}
    outputs = {o.port: _bound_output(o, service, instance) for o in ports.outputs}
    return Binding(service, instance, inputs, outputs)


def published(deployment: Deployment) -> list[KeySpec]:
    """Every concrete key the deployment's instances publish (outputs off by parameter excluded)."""
    specs = []
    for service, instance in deployment.instances():
        params = deployment.params(service, instance)
        for out in ports_of(service).outputs:
            if out.enabled_by is not None and params.get(out.enabled_by) is not True:
                continue
            for key in _bound_output(out, service, instance).keys.values():
                specs.append(KeySpec(key, out.msgtype, service, out.rate_hz, out.doc, out.on_change,
                                     instance, out.port))
    return list({s.key: s for s in specs}.values())  # the clock: one key, whoever publishes it


def intersects(a: str, b: str) -> bool:
    """Whether two key expressions share a key (Zenoh's rules: ``*`` one chunk, ``**`` any)."""
    return zenoh.KeyExpr(a).intersects(zenoh.KeyExpr(b))


def edges(deployment: Deployment) -> tuple[list[Edge], list[str]]:
    """The deployment's dataflow and its problems (a subscription no instance publishes to)."""
    keys = published(deployment)
    out: list[Edge] = []
    problems: list[str] = []
    for service, instance in deployment.instances():
        try:
            binding = bind(deployment, service, instance)
        except ConfigError as exc:
            problems.append(str(exc))
            continue
        for inp in binding.inputs.values():
            for source, expr in zip(inp.sources, inp.key_exprs, strict=True):
                hits = [k for k in keys if intersects(expr, k.key)]
                if not hits:
                    problems.append(f"{service}/{instance}.{inp.port} reads {expr} ({source}): "
                                    "no instance of this deployment publishes it")
                producers = {(k.service, k.instance, k.port): k for k in hits}
                for (svc, inst, port), k in producers.items():
                    out.append(Edge(f"{svc}/{inst}", port, f"{service}/{instance}", inp.port, inp.msgtype,
                                    k.rate_hz, inp.queue, expr, inp.only))
    if deployment.clock == "sim" and not any(k.key == "xm/clock" for k in keys):
        problems.append("clock = \"sim\" but no instance publishes xm/clock (a world service)")
    return out, problems


def start_order(deployment: Deployment) -> list[tuple[str, str]]:
    """Instances in the deployment's order, services that host devices first."""
    return sorted(deployment.instances(), key=lambda si: not ports_of(si[0]).hosts_devices)
