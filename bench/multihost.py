"""Recorded rates across two hosts against one host (docs/multihost.md; root only).

The deployment of tests/integration/test_multihost.py (world, gloves, cameras and robot on one
host; recorder, policy and trajopt on the other) runs twice in network namespaces: first every
service in one namespace (`xm up` without `--host`), then split over two namespaces whose routers
link over mutual TLS with access control. Each time the recorder records ``--seconds``; per key,
the rate across the link is compared with the one-host rate. Writes .bench/multihost.json.
Target: every key within 5 % of the one-host rate, nothing dropped.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from deploy import certs, netns  # noqa: E402
from tests.integration.test_multihost import ROOT, ROUTER, deployment, probe  # noqa: E402

KEYS = ("xm/glove/left/tactile", "xm/glove/right/tactile", "xm/camhub/cam0/image", "xm/clock",
        "xm/robot/workcell/state")


def start(ns: str, dep: Path, host: str | None, log: Path) -> subprocess.Popen:
    argv = [sys.executable, "-m", "shared.cli", "up", str(dep), "--quiet", "--no-standby"]
    return netns.run(ns, argv + (["--host", host] if host else []), cwd=ROOT, stdout=log.open("w"),
                     stderr=subprocess.STDOUT, start_new_session=True)


def record(ns: str, seconds: float, path: Path) -> dict:
    flowing = probe(ns, "flowing", ROUTER, 240, *KEYS)
    if not flowing["ok"]:
        raise RuntimeError(f"streams not flowing in {ns}: {flowing}")
    rec = probe(ns, "record", ROUTER, seconds, path, timeout=seconds + 240)
    stop_reply = rec["stop"][0]
    return {"rates_hz": {k: n / seconds for k, n in stop_reply["messages"].items()},
            "dropped": rec["health"][0].get("dropped", {})}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=30.0, help="recording length (default %(default)s)")
    args = parser.parse_args(argv)
    why = netns.available()
    if why:
        print(f"error: {why}", file=sys.stderr)
        return 2
    tmp = Path(tempfile.mkdtemp(prefix="xm-multihost-"))
    names = ("xmbench_a", "xmbench_b")
    pair = netns.up(*names, subnet=99)
    dep = deployment(tmp, pair.addresses)
    certs.main([str(dep)])
    result: dict = {"seconds": args.seconds, "loadavg_start": os.getloadavg()}
    try:
        procs = [start(names[0], dep, None, tmp / "one.log")]
        try:
            result["one_host"] = record(names[0], args.seconds, tmp / "one.mcap")
        finally:
            netns.stop(procs)
        procs = [start(names[0], dep, "cameras", tmp / "cameras.log"),
                 start(names[1], dep, "learner", tmp / "learner.log")]
        try:
            result["two_hosts"] = record(names[1], args.seconds, tmp / "two.mcap")
        finally:
            netns.stop(procs)
    finally:
        netns.down(*names)
    one, two = result["one_host"]["rates_hz"], result["two_hosts"]["rates_hz"]
    result["ratio"] = {k: two.get(k, 0.0) / one[k] for k in KEYS if one.get(k)}
    result["worst_deviation"] = max(abs(r - 1.0) for r in result["ratio"].values())
    result["loadavg_end"] = os.getloadavg()
    result["target"] = {"max_deviation": 0.05, "dropped": 0}
    Path(".bench").mkdir(exist_ok=True)
    Path(".bench/multihost.json").write_text(json.dumps(result, indent=2))
    for k in KEYS:
        print(f"{k:<28} one host {one.get(k, 0):7.1f} Hz   two hosts {two.get(k, 0):7.1f} Hz")
    print(f"worst deviation {result['worst_deviation']:.1%} (target 5 %); dropped: one host "
          f"{result['one_host']['dropped'] or 0}, two hosts {result['two_hosts']['dropped'] or 0}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
