"""Command-line tools as Zenoh clients of a running deployment: connection options and connecting."""

from __future__ import annotations

import argparse
import sys

import zenoh

from shared.config import ConfigError, load_deployment
from shared.runtime import open_client


def add_connection_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--deployment", default="deploy/sim.toml",
                        help="deployment whose router to connect to (default: %(default)s)")
    parser.add_argument("--router", metavar="ENDPOINT", help="router endpoint, e.g. tcp/127.0.0.1:7447 "
                        "(overrides the deployment's)")


def connect(args: argparse.Namespace) -> tuple[zenoh.Session | None, str, str]:
    """(session or None, router, deployment name); on failure the reason is printed to stderr."""
    name = ""
    router = args.router
    if router is None:
        try:
            deployment = load_deployment(args.deployment)
        except ConfigError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return None, "", ""
        router, name = deployment.router, deployment.name
    try:
        return open_client(router), router, name
    except Exception as exc:
        print(f"error: no router reachable at {router} ({str(exc).split(' at ')[0].strip()}); start the "
              f"workcell first (`xm up {args.deployment}`) or give --deployment/--router", file=sys.stderr)
        return None, router, name
