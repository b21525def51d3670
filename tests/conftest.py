"""Helpers for tests that run real processes: free ports, temporary deployments, a router,
service subprocesses with captured logs, Zenoh queries and subscriptions, waits on conditions, and
the host's end of a control board's serial port."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import re
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import serial
import zenoh

from shared import keys
from shared.process_group import stop_group
from shared.protocols import robot_board as rb
from shared.runtime import open_client, open_router

ROOT = Path(__file__).resolve().parents[1]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def free_endpoint() -> str:
    return f"tcp/127.0.0.1:{free_port()}"


def _toml_value(value: object) -> str:
    """A TOML value: tables inline (``inputs = { truth = [] }``), everything else as JSON, which TOML shares."""
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{k} = {_toml_value(v)}" for k, v in value.items()) + " }"
    if isinstance(value, list):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    return json.dumps(value)


def write_deployment(path: Path, router: str, services: dict[str, dict[str, dict]],
                     clock: str = "wall") -> Path:
    """A deployment TOML with one table per instance; run_dir is ``<path's folder>/run``."""
    lines = ["[deployment]", 'name = "test"', f'router = "{router}"', f'clock = "{clock}"',
             f'run_dir = "{path.parent / "run"}"', ""]
    for svc, instances in services.items():
        for inst, params in instances.items():
            lines.append(f"[services.{svc}.{inst}]")
            lines += [f"{k} = {_toml_value(v)}" for k, v in params.items()]
            lines.append("")
    path.write_text("\n".join(lines))
    return path


@pytest.fixture
def router():
    """``(endpoint, session)``: a Zenoh router on a free port; the session doubles as the test's client."""
    endpoint = free_endpoint()
    session = open_router(endpoint)
    yield endpoint, session
    session.close()


class ServiceProcess:
    """``python -m services.<service> --deployment D --instance I`` in its own process group.

    Output goes to ``log``; ``output()`` reads it for assertion messages. Usable as a context manager."""

    def __init__(self, service: str, deployment: Path, instance: str, log: Path,
                 env: dict[str, str] | None = None) -> None:
        self.log = log
        self._log = log.open("w")
        argv = [sys.executable, "-m", f"services.{service}", "--deployment", str(deployment),
                "--instance", instance]
        self.proc = subprocess.Popen(argv, cwd=ROOT, stdout=self._log, stderr=subprocess.STDOUT,
                                     start_new_session=True, env={**os.environ, **(env or {})})

    def alive(self) -> bool:
        return self.proc.poll() is None

    def stop(self, timeout: float = 10.0) -> int:
        """SIGTERM, then SIGKILL after ``timeout``; returns the exit status (-15 when killed by SIGTERM)."""
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGTERM)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait()
        self._log.close()
        return self.proc.returncode

    def kill(self) -> int:
        """SIGKILL, as a crash or power loss would end it."""
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait()
        self._log.close()
        return self.proc.returncode

    def output(self) -> str:
        return self.log.read_text(errors="replace")

    def __enter__(self) -> ServiceProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def query_json(session, selector: str, payload: dict | None = None, timeout: float = 2.0) -> list[dict]:
    """Replies of a queryable (``@health``, ``@cmd/<verb>``) as dicts; [] when nobody answered."""
    kwargs = {"payload": json.dumps(payload)} if payload is not None else {}
    return [json.loads(r.ok.payload.to_bytes()) for r in session.get(selector, timeout=timeout, **kwargs)
            if r.ok is not None]


def wait_for(predicate: Callable[[], Any], timeout: float = 20.0, period: float = 0.2) -> Any:
    """The first truthy value of ``predicate()`` within ``timeout`` seconds, else None."""
    deadline = time.time() + timeout
    while time.time() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(period)
    return None


def _poll(predicate: Callable[[], Any], deadline: float, timeout: float, what: str | Callable[[], str]) -> Any:
    """``predicate()``; past the deadline a falsy value fails the test, saying what was awaited."""
    value = predicate()
    if not value and time.monotonic() >= deadline:
        pytest.fail(f"timed out after {timeout} s waiting for {what() if callable(what) else what}")
    return value


def wait_until(predicate: Callable[[], Any], timeout: float, what: str | Callable[[], str],
               period: float = 0.05) -> Any:
    """The first truthy value of ``predicate()`` within ``timeout`` seconds; otherwise the test fails
    saying what it waited for (``what``, or ``what()`` for context read only then, like a service log)."""
    deadline = time.monotonic() + timeout
    while not (value := _poll(predicate, deadline, timeout, what)):
        time.sleep(period)
    return value


async def wait_until_async(predicate: Callable[[], Any], timeout: float, what: str | Callable[[], str],
                           period: float = 0.01) -> Any:
    """``wait_until`` inside an event loop: other tasks run while it waits."""
    deadline = time.monotonic() + timeout
    while not (value := _poll(predicate, deadline, timeout, what)):
        await asyncio.sleep(period)
    return value


def wait_healthy(session, service: str, instance: str, proc: ServiceProcess | None = None,
                 timeout: float = 20.0) -> dict:
    """The service's first @health report; fails the test (with its log) when none comes."""
    def report() -> list[dict]:
        if proc is not None and not proc.alive():
            pytest.fail(f"{service}/{instance} exited with {proc.proc.returncode}:\n{proc.output()[-3000:]}")
        return query_json(session, f"xm/{service}/{instance}/@health")

    got = wait_for(report, timeout)
    if not got:
        pytest.fail(f"no @health from {service}/{instance} within {timeout} s"
                    + (f":\n{proc.output()[-3000:]}" if proc is not None else ""))
    return got[0]


class Collector:
    """Samples of a key expression: ``(key, payload bytes)`` in arrival order; ``close()`` undeclares."""

    def __init__(self, session, key_expr: str) -> None:
        self.samples: list[tuple[str, bytes]] = []
        self._sub = session.declare_subscriber(key_expr, self._on)

    def _on(self, sample) -> None:
        self.samples.append((str(sample.key_expr), sample.payload.to_bytes()))

    def payloads(self, key: str) -> list[bytes]:
        return [p for k, p in self.samples if k == key]

    def close(self) -> None:
        self._sub.undeclare()


def query_router(router: str, selector: str, timeout: float = 3.0) -> list[dict]:
    """Replies to ``selector`` through a fresh client of ``router``; [] while no router is up."""
    try:
        session = open_client(router)
    except zenoh.ZError:
        return []
    try:
        return [json.loads(r.ok.payload.to_bytes()) for r in session.get(selector, timeout=timeout) if r.ok]
    finally:
        session.close()


@contextlib.contextmanager
def sim_workcell(tmp: Path, timeout: float = 180.0) -> Iterator[dict]:
    """The whole simulated workcell (deploy/sim.toml) through ``xm up`` on a free router port, with its
    run directory, recordings and panel port private to ``tmp``; up once every registered key is being
    published. Yields ``{"router", "deployment", "tmp", "proc"}``; SIGINT (then SIGKILL) on exit."""
    text = (ROOT / "deploy/sim.toml").read_text()
    router = free_endpoint()
    text = re.sub(r'router = "[^"]*"', f'router = "{router}"', text)
    text = re.sub(r'run_dir = "[^"]*"', f'run_dir = "{tmp}/run"', text)
    # The same cell whether or not this checkout has trained a policy: the naive fallback (the
    # learned service has its own contract test).
    text = re.sub(r'first_network = "[^"]*"', 'first_network = ""', text)  # and no training job beside it
    text = re.sub(r'checkpoint = "[^"]*"', f'checkpoint = "{tmp}/no-policy.pt"', text)
    text = re.sub(r"port = 8080", f"port = {free_port()}", text)
    text = re.sub(r'directory = "[^"]*"', f'directory = "{tmp}/recordings"', text)
    deployment = tmp / "sim.toml"
    deployment.write_text(text)
    registered = {s.key for s in keys.REGISTRY}
    with xm_up(deployment, tmp / "up.log") as proc:

        def missing() -> set[str]:
            reports = query_router(router, "xm/**/@health") if proc.poll() is None else []
            return registered - {k for r in reports for k, hz in r.get("published_hz", {}).items() if hz > 0}

        wait_until(lambda: not missing(), timeout, lambda: f"the workcell to publish every registered key; missing "
                   f"{sorted(missing())}; log: {(tmp / 'up.log').read_text()[-3000:]}", period=1.0)
        yield {"router": router, "deployment": deployment, "tmp": tmp, "proc": proc}


@contextlib.contextmanager
def xm_up(deployment: Path, log_path: Path, *flags: str) -> Iterator[subprocess.Popen]:
    """``xm up <deployment> --quiet <flags>`` in its own process group, output to ``log_path``;
    SIGINT (then SIGKILL) to the whole group on exit."""
    log = log_path.open("w")
    proc = subprocess.Popen([sys.executable, "-m", "shared.cli", "up", str(deployment), "--quiet", *flags],
                            cwd=ROOT, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        yield proc
    finally:
        stop_group(proc, 20)
        log.close()


def run_xm(*args: str, timeout: float = 60.0) -> subprocess.CompletedProcess:
    """``xm <args>`` as a subprocess from the repository root, output captured as text."""
    return subprocess.run([sys.executable, "-m", "shared.cli", *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=timeout)


class BoardHost:
    """The test as the host on a control board's serial port (the world's simulated board): it sends
    command frames and collects the board's feedback (``feedback``, in arrival order)."""

    COMMAND_PERIOD_S = 0.004  # the robot service's 250 Hz

    def __init__(self, port: Path) -> None:
        self.port = serial.Serial(str(port), timeout=0)
        self.decoder = rb.StreamDecoder()
        self.feedback: list[rb.FeedbackFrame] = []

    def read(self) -> None:
        self.feedback += [m for m in self.decoder.feed(self.port.read(65536)) if isinstance(m, rb.FeedbackFrame)]

    def stream(self, cmd: rb.CommandFrame | None, until: Callable[[], Any], timeout: float, what: str) -> Any:
        """Sends ``cmd`` every command period, its sequence counting up (None: silence), reading the
        feedback, until ``until()`` is true; fails the test after ``timeout`` s."""
        def step() -> Any:
            if cmd is not None:
                self.port.write(rb.encode_command(cmd))
                cmd.sequence += 1
            self.read()
            return until()

        return wait_until(step, timeout, what, period=self.COMMAND_PERIOD_S)

    def brake_trial(self, cmd: rb.CommandFrame, stream_s: float) -> float:
        """A command stream of ``stream_s`` seconds, then silence: the board time (s) from the last
        command to the board's first brake report that names it."""
        t_end = time.monotonic() + stream_s
        self.stream(cmd, lambda: time.monotonic() > t_end, stream_s + 5, "the end of the command stream")
        final = cmd.sequence - 1
        # Matched by sequence: under CPU load the report may already have come during the stream.
        brake = self.stream(None, lambda: next((m for m in self.feedback if m.watchdog_expired and
                                                m.last_command_sequence == final), None),
                            5.0, f"the board's brake report after command {final}")
        return (brake.timestamp_us - brake.last_command_us) * 1e-6

    def close(self) -> None:
        self.port.close()
