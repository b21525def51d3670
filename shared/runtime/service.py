"""Entry point shared by every service: arguments, deployment, node, signals, clean shutdown.

A service module provides a class with a nested ``Params`` dataclass and::

    def __init__(self, node: Node, params: Params): ...   # node.input / node.output: its declared ports
    async def run(self) -> None: ...                        # optional main loop (default: serve forever)
    async def close(self) -> None: ...                      # optional: release devices

its ``ports.py`` declares ``PORTS`` (shared/ports.py), and its ``__main__.py`` calls
``service_main("glove", GloveService)``.

With ``--standby`` the process stops after its imports and waits for a line on stdin before it
connects: the supervisor keeps such a spare per service and hands over to it when the service
dies, so a restart skips the interpreter's start, the imports and the message codecs and schema
hashes of its ports (the type store alone takes ~0.2 s to build). A service class may also
define ``prepare(params)`` (a classmethod): work that needs no connection (decoders, solvers,
networks, renderers), which a spare does before it waits, so the takeover skips it too; one that
also declares a ``deployment`` parameter gets the loaded deployment (camhub: the world's task).
"""

from __future__ import annotations

import argparse
import asyncio
import inspect
import os
import signal
import sys
import time
from pathlib import Path
from typing import Any

from shared import msgs
from shared.config import ConfigError, load_deployment
from shared.runtime.logs import fields, setup_logging
from shared.runtime.node import Node
from shared.runtime.schemas import type_hash
from shared.runtime.zsession import EndpointError, open_client
from shared.wiring import bind

STANDBY_READY = "standby: imported and prepared, waiting"


def parse_args(service: str, argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog=f"python -m services.{service}",
                                     description=f"crossmodal {service} service")
    parser.add_argument("--deployment", default="deploy/sim.toml", help="deployment TOML file")
    parser.add_argument("--instance", required=True, help="instance name within the deployment")
    parser.add_argument("--standby", action="store_true",
                        help="import, then wait for a line on stdin before starting (the supervisor's spare)")
    return parser.parse_args(argv)


async def run_node(service: str, cls: type, deployment_path: str, instance: str,
                   stop: asyncio.Event | None = None, woken_at: float | None = None) -> None:
    """Runs one service instance until ``stop`` (or SIGINT/SIGTERM); ``woken_at``: the monotonic
    time a standby process was told to start (its start-up is counted from there)."""
    deployment = load_deployment(deployment_path)
    params = deployment.service_params(cls.Params, service, instance)
    ports = bind(deployment, service, instance)
    log = setup_logging(f"{service}/{instance}")
    session = open_client(deployment.router)
    node = Node(service, instance, session, deployment.clock, log, ports)
    stop = stop or asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    impl: Any = None
    try:
        impl = cls(node, params)
        if node.status == "starting":  # the service may already have reported itself degraded
            node.set_status("ok")
        if woken_at is not None:
            log.info("ready", extra=fields(since_taken_over_s=round(time.monotonic() - woken_at, 3)))
        elif (age := process_age()) is not None:
            log.info("ready", extra=fields(since_process_start_s=round(age, 3)))
        main = node.spawn(impl.run() if hasattr(impl, "run") else stop.wait(), name="run")
        stopper = asyncio.ensure_future(stop.wait())
        await asyncio.wait({main, stopper}, return_when=asyncio.FIRST_COMPLETED)
        stopper.cancel()
        if main.done() and not main.cancelled() and main.exception() is not None:
            raise main.exception()
        main.cancel()  # stop the loop before its devices are closed under it
        await asyncio.gather(main, return_exceptions=True)
    finally:
        log.info("shutting down")
        if impl is not None and hasattr(impl, "close"):
            try:
                await asyncio.wait_for(impl.close(), 3.0)
            except Exception as exc:
                log.warning("close failed: %r", exc)
        await node.close()
        session.close()


def process_age() -> float | None:
    """Seconds since this process started (interpreter start and imports included); None off Linux."""
    try:
        start_ticks = int(Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()[19])
        uptime = float(Path("/proc/uptime").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return None
    return uptime - start_ticks / os.sysconf("SC_CLK_TCK")


def warm_codecs(msgtypes: set[str]) -> None:
    """Build the codecs and schema hashes of these message types now (each is cached)."""
    for msgtype in sorted(msgtypes):
        if "/msg/" in msgtype:  # a registered type, not "raw"
            msgs.decoder(msgtype)
            msgs.pieces_writer(msgtype)
            type_hash(msgtype)


def prepare_spare(service: str, cls: type, deployment_path: str, instance: str) -> None:
    """The ports' codecs and ``cls.prepare(params)`` ahead of a takeover; a failure is left to the
    real start to report."""
    try:
        deployment = load_deployment(deployment_path)
        ports = bind(deployment, service, instance)
        warm_codecs({p.msgtype for p in (*ports.inputs.values(), *ports.outputs.values())})
        if not hasattr(cls, "prepare"):
            return
        params = deployment.service_params(cls.Params, service, instance)
        if "deployment" in inspect.signature(cls.prepare).parameters:
            cls.prepare(params, deployment=deployment)
        else:
            cls.prepare(params)
    except Exception as exc:  # the service's own start meets the same problem and reports it
        print(f"standby: prepare failed ({exc!r}); the service does it when it starts", file=sys.stderr)


def service_main(service: str, cls: type, argv: list[str] | None = None) -> None:
    args = parse_args(service, argv)
    woken_at = None
    if args.standby:
        prepare_spare(service, cls, args.deployment, args.instance)
        print(STANDBY_READY, flush=True)  # the supervisor reports the spare ready from here on
        if not sys.stdin.readline():  # EOF: the supervisor is gone, nobody needs this spare
            return
        woken_at = time.monotonic()
    try:
        asyncio.run(run_node(service, cls, args.deployment, args.instance, woken_at=woken_at))
    except (ConfigError, EndpointError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)
