"""Helpers for tests that run real processes: free ports, temporary deployments, a router."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def write_deployment(path: Path, router: str, services: dict[str, dict[str, dict]], clock: str = "wall") -> Path:
    lines = ["[deployment]", 'name = "test"', f'router = "{router}"', f'clock = "{clock}"',
             f'run_dir = "{path.parent / "run"}"', ""]
    for svc, instances in services.items():
        for inst, params in instances.items():
            lines.append(f"[services.{svc}.{inst}]")
            lines += [f"{k} = {json.dumps(v)}" for k, v in params.items()]
            lines.append("")
    path.write_text("\n".join(lines))
    return path


@pytest.fixture
def router():
    from shared.runtime import open_router

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    session = open_router(endpoint)
    yield endpoint, session
    session.close()


class ServiceProcess:
    def __init__(self, service: str, deployment: Path, instance: str, log: Path) -> None:
        self.log = log
        self._log = log.open("w")
        self.proc = subprocess.Popen([sys.executable, "-m", f"services.{service}", "--deployment", str(deployment),
                                      "--instance", instance], cwd=ROOT, stdout=self._log, stderr=subprocess.STDOUT,
                                     start_new_session=True)

    def stop(self) -> int:
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGTERM)
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait()
        self._log.close()
        return self.proc.returncode

    def output(self) -> str:
        return self.log.read_text(errors="replace")


def query_json(session, selector: str, payload: dict | None = None, timeout: float = 2.0) -> list[dict]:
    kwargs = {"payload": json.dumps(payload)} if payload is not None else {}
    return [json.loads(r.ok.payload.to_bytes()) for r in session.get(selector, timeout=timeout, **kwargs)
            if r.ok is not None]


def wait_for(predicate, timeout: float = 20.0, period: float = 0.2):
    deadline = time.time() + timeout
    while time.time() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(period)
    return None
