"""Two hosts on one Linux machine: network namespaces joined by a veth pair (root only).

For trying a multi-host deployment without a second computer and for the tests: each namespace
has its own loopback (each host's router listens on the deployment's ``router`` endpoint there)
and one address on the link (10.77.<n>.1 and .2); nothing else is reachable from it.
``python -m deploy.netns up A B`` creates them, ``down A B`` removes them; ``run(ns, argv)`` starts
a process inside one, ``stop`` ends those.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
from dataclasses import dataclass


class NetnsError(RuntimeError):
    """Namespaces cannot be made here; the message says why."""


@dataclass(frozen=True)
class Pair:
    names: tuple[str, str]
    addresses: tuple[str, str]


def available() -> str | None:
    """Why namespaces cannot be made here (None: they can)."""
    if sys.platform != "linux":
        return "network namespaces need Linux"
    if os.geteuid() != 0:
        return "network namespaces need root"
    if shutil.which("ip") is None:
        return "the `ip` command (iproute2) is missing: apt-get install iproute2"
    return None


def _ip(*args: str) -> None:
    r = subprocess.run(["ip", *args], capture_output=True, text=True, check=False)
    if r.returncode != 0:
        raise NetnsError(f"ip {' '.join(args)}: {r.stderr.strip()}")


def up(a: str, b: str, subnet: int = 77) -> Pair:
    """Namespaces ``a`` and ``b`` linked by a veth pair, 10.77.``subnet``.1/.2 (``subnet`` 0-255)."""
    why = available()
    if why:
        raise NetnsError(why)
    down(a, b)
    addresses = (f"10.77.{subnet}.1", f"10.77.{subnet}.2")
    _ip("netns", "add", a)
    _ip("netns", "add", b)
    veth = (f"v{a}"[:15], f"v{b}"[:15])
    _ip("link", "add", veth[0], "netns", a, "type", "veth", "peer", "name", veth[1], "netns", b)
    for ns, dev, addr in ((a, veth[0], addresses[0]), (b, veth[1], addresses[1])):
        _ip("-n", ns, "addr", "add", f"{addr}/24", "dev", dev)
        _ip("-n", ns, "link", "set", dev, "up")
        _ip("-n", ns, "link", "set", "lo", "up")
    return Pair((a, b), addresses)


def down(*names: str) -> None:
    """Remove the namespaces (their veth ends go with them); missing ones are fine."""
    for ns in names:
        subprocess.run(["ip", "netns", "del", ns], capture_output=True, check=False)


def run(ns: str, argv: list[str], **popen) -> subprocess.Popen:
    """``argv`` inside namespace ``ns``."""
    return subprocess.Popen(["ip", "netns", "exec", ns, *argv], **popen)


def stop(procs: list[subprocess.Popen], timeout: float = 30.0) -> None:
    """Ctrl-C to each process group started by ``run`` (``start_new_session=True``), then a kill
    for any still running after ``timeout`` seconds."""
    for p in procs:
        try:
            os.killpg(p.pid, signal.SIGINT)
        except ProcessLookupError:
            pass
    for p in procs:
        try:
            p.wait(timeout)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)


def main(argv: list[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    if len(args) != 3 or args[0] not in ("up", "down"):
        print("usage: python -m deploy.netns up|down NS_A NS_B", file=sys.stderr)
        return 2
    try:
        if args[0] == "up":
            pair = up(args[1], args[2])
            print(f"{pair.names[0]}: {pair.addresses[0]}   {pair.names[1]}: {pair.addresses[1]}")
        else:
            down(args[1], args[2])
    except NetnsError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
