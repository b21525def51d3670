"""``xm graph``: a deployment's dataflow as text and as an SVG drawn by Graphviz's ``dot``.

Every edge is one line: producer/output -> consumer/input, message type, nominal rate, queue
policy. The edges come from the services' port declarations (services/*/ports.py) and the
deployment's remaps (shared/wiring.py); the same code wires the running services.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
from pathlib import Path

from shared.config import ConfigError, Deployment, load_deployment
from shared.ports import ports_of
from shared.wiring import Edge, bind, edges, published, start_order

DEFAULT_OUT = "runs/graph/{name}.svg"  # runs/ is not tracked


def _rate(hz: float) -> str:
    return f"{hz:g} Hz"


def _output(e: Edge) -> str:
    """The producer's port, with the one key read of a fanned-out port: ``image[cam0]``."""
    return f"{e.output}[{e.only}]" if e.only else e.output


def unconnected(deployment: Deployment) -> list[str]:
    """Inputs the deployment disconnects on purpose (``inputs = { port = [] }``)."""
    out = []
    for service, instance in deployment.instances():
        try:
            binding = bind(deployment, service, instance)
        except ConfigError:
            continue  # reported by edges()
        out += [f"{service}/{instance}.{i.port}" for i in binding.inputs.values() if not i.sources]
    return out


def unread(deployment: Deployment, graph: list[Edge]) -> list[str]:
    """Outputs no instance of the deployment subscribes (recorder and panel tools may still)."""
    read = {(e.producer, e.output) for e in graph}
    seen = {}
    for spec in published(deployment):
        seen.setdefault((f"{spec.service}/{spec.instance}", spec.port), spec)
    return [f"{p}/{port}" for (p, port) in seen if (p, port) not in read and port != "clock"]


def text(deployment: Deployment) -> tuple[str, list[str]]:
    """The printed dataflow, and the wiring problems (empty when every input has a publisher)."""
    graph, problems = edges(deployment)
    lines = [f"deployment {deployment.name} ({deployment.path}): clock {deployment.clock}, "
             f"robot {deployment.robot}", "", "instances (start order)"]
    for service, instance in start_order(deployment):
        ports = ports_of(service)
        first = "  [hosts devices: started first]" if ports.hosts_devices else ""
        lines.append(f"  {service + '/' + instance:<18} {ports.doc}{first}")
    rows = [(f"{e.producer}/{_output(e)}", f"{e.consumer}/{e.input}", e.msgtype, _rate(e.rate_hz), str(e.queue))
            for e in graph]
    clock = next((k for k in published(deployment) if k.key == "xm/clock"), None)
    if deployment.clock == "sim" and clock is not None:  # the node subscribes it itself (shared/runtime)
        rows.append((f"{clock.service}/{clock.instance}/clock", "every instance (clock = \"sim\")",
                     clock.msgtype, _rate(clock.rate_hz), "latest(1)"))
    head = ("producer/output", "consumer/input", "type", "rate", "queue")
    widths = [max(len(r[i]) for r in [head, *rows]) for i in range(5)]
    lines += ["", "edges"]
    lines += ["  " + "  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)).rstrip()
              for r in [head, *rows]]
    if loose := unconnected(deployment):
        lines += ["", "not connected in this deployment (inputs = { port = [] })"] + [f"  {p}" for p in loose]
    if quiet := unread(deployment, graph):
        lines += ["", "outputs no service of this deployment reads (the recorder may)"] + [f"  {q}" for q in quiet]
    if problems:
        lines += ["", "PROBLEMS"] + [f"  {p}" for p in problems]
    return "\n".join(lines), problems


def dot_source(deployment: Deployment) -> str:
    """Graphviz DOT: one box per instance, one arrow per edge labelled with ports, type, rate, queue."""
    graph, _ = edges(deployment)
    out = ["digraph dataflow {", "  rankdir=LR;", '  node [shape=box, style=rounded, fontname="Helvetica"];',
           '  edge [fontname="Helvetica", fontsize=9];',
           f'  label="{deployment.name}: {deployment.path}"; labelloc=t;']
    for service, instance in deployment.instances():
        out.append(f'  "{service}/{instance}" [label="{service}/{instance}\\n{ports_of(service).doc}"];')
    for e in graph:
        label = f"{_output(e)} → {e.input}\\n{e.msgtype.split('/')[-1]}, {_rate(e.rate_hz)}, {e.queue}"
        out.append(f'  "{e.producer}" -> "{e.consumer}" [label="{label}"];')
    out.append("}")
    return "\n".join(out) + "\n"


def write_svg(deployment: Deployment, path: Path) -> str:
    """Draw the SVG with ``dot``; without Graphviz write the DOT file and say how to get the SVG."""
    path.parent.mkdir(parents=True, exist_ok=True)
    source = dot_source(deployment)
    dot = shutil.which("dot")
    if dot is None:
        dot_path = path.with_suffix(".dot")
        dot_path.write_text(source)
        return (f"no SVG: Graphviz's `dot` is not installed (apt-get install graphviz); "
                f"wrote {dot_path}, render it with `dot -Tsvg {dot_path} -o {path}`")
    done = subprocess.run([dot, "-Tsvg", "-o", str(path)], input=source, text=True, capture_output=True,
                          timeout=60)
    if done.returncode != 0:
        return f"no SVG: dot failed: {done.stderr.strip()[:500]}"
    return f"wrote {path}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="xm graph", description="Print a deployment's dataflow (every edge: producer/output -> "
        "consumer/input, message type, nominal rate, queue policy) and draw it as an SVG with Graphviz. "
        "Exit status 1 when an input has no publisher in the deployment.")
    parser.add_argument("deployment", nargs="?", default="deploy/sim.toml", help="deployment TOML file "
                        "(default: %(default)s)")
    parser.add_argument("--svg", metavar="PATH",
                        help="where to write the SVG (default: runs/graph/<deployment file name>.svg)")
    parser.add_argument("--no-svg", action="store_true", help="only print")
    parser.add_argument("--dot", action="store_true", help="print the Graphviz DOT source instead of the table")
    args = parser.parse_args(argv)
    try:
        deployment = load_deployment(args.deployment)
        report, problems = text(deployment)
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(dot_source(deployment) if args.dot else report)
    if not args.no_svg:
        path = Path(args.svg or DEFAULT_OUT.format(name=Path(args.deployment).stem))
        print(write_svg(deployment, path), file=sys.stderr)
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
