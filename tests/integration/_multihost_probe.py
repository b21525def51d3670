"""Run inside one namespace of the multi-host test (deploy/netns.py); prints one JSON line.

  record ENDPOINT SECONDS PATH          wait for the recorder, record SECONDS, report per-key counts
  health ENDPOINT KEY TIMEOUT           wait until KEY's @health answers
  flowing ENDPOINT TIMEOUT KEY...       wait until a sample of every KEY arrived
  listen ENDPOINT KEYEXPR SECONDS       count samples per key
  publish ENDPOINT SECONDS KEY...       put on each KEY every 50 ms for SECONDS
  connect ENDPOINT CA [CERT KEY]        open a client over TLS (with or without a certificate)
"""

from __future__ import annotations

import collections
import json
import sys
import time
from pathlib import Path

import zenoh

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from shared.runtime import open_client  # noqa: E402
from shared.runtime.zsession import _config  # noqa: E402


def query(session, selector: str, payload: dict | None = None, timeout: float = 5.0) -> list[dict]:
    kwargs = {"payload": json.dumps(payload)} if payload is not None else {}
    return [json.loads(r.ok.payload.to_bytes()) for r in session.get(selector, timeout=timeout, **kwargs)
            if r.ok is not None]


def wait_health(session, key: str, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if query(session, key, timeout=2.0):
            return True
        time.sleep(0.5)
    return False


def main(argv: list[str]) -> dict:
    cmd, endpoint = argv[0], argv[1]
    if cmd == "connect":
        extra = {"transport/link/tls/root_ca_certificate": argv[2], "connect/timeout_ms": 10000}
        if len(argv) > 3:
            extra |= {"transport/link/tls/connect_certificate": argv[3],
                      "transport/link/tls/connect_private_key": argv[4], "transport/link/tls/enable_mtls": True}
        try:
            zenoh.open(_config("client", connect=[endpoint], extra=extra)).close()
            return {"connected": True}
        except Exception as exc:  # zenoh raises ZError, not exported under one name across versions
            return {"connected": False, "error": str(exc)[:300]}
    deadline = time.monotonic() + 120  # the host's router may still be starting
    while True:
        try:
            session = open_client(endpoint)
            break
        except zenoh.ZError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.5)
    try:
        if cmd == "health":
            return {"ok": wait_health(session, argv[2], float(argv[3]))}
        if cmd == "flowing":
            deadline, keys, seen = time.monotonic() + float(argv[2]), argv[3:], set()
            subs = [session.declare_subscriber(k, lambda s: seen.add(str(s.key_expr))) for k in keys]
            while not seen >= set(keys) and time.monotonic() < deadline:
                time.sleep(0.2)
            del subs
            return {"ok": seen >= set(keys), "missing": sorted(set(keys) - seen)}
        if cmd == "record":
            seconds, path = float(argv[2]), argv[3]
            if not wait_health(session, "xm/recorder/main/@health", 120):
                return {"ok": False, "error": "no recorder"}
            start = query(session, "xm/recorder/main/@cmd/start", {"path": path})
            time.sleep(seconds)
            stop = query(session, "xm/recorder/main/@cmd/stop", {}, timeout=30)
            health = query(session, "xm/recorder/main/@health")
            return {"start": start, "stop": stop, "health": health}
        if cmd == "listen":
            counts: collections.Counter[str] = collections.Counter()
            session.declare_subscriber(argv[2], lambda s: counts.update([str(s.key_expr)]))
            time.sleep(float(argv[3]))
            return dict(counts)
        if cmd == "publish":
            seconds, keys = float(argv[2]), argv[3:]
            pubs = [session.declare_publisher(k) for k in keys]
            sent = 0
            deadline = time.monotonic() + seconds
            while time.monotonic() < deadline:
                for p in pubs:
                    p.put(b"probe")
                sent += 1
                time.sleep(0.05)
            return {"sent_per_key": sent}
    finally:
        session.close()
    raise SystemExit(f"unknown command {cmd!r}")


if __name__ == "__main__":
    print(json.dumps(main(sys.argv[1:])), flush=True)
