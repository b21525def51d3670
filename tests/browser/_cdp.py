"""Headless Chromium driven over the DevTools protocol (no selenium): open a page, evaluate, screenshot.

Chromium runs in its own process group with a fresh profile and is killed with the group on close,
so a failing test never leaves a browser behind.
"""

from __future__ import annotations

import base64
import json
import os
import shutil
import signal
import subprocess
import time
import urllib.request
from pathlib import Path
from typing import Any

from websockets.sync.client import connect

FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
         "--disable-component-update", "--disable-sync", "--no-first-run", "--disable-quic",
         # WebGL without a GPU: the software rasterizer, which newer Chromium gates behind this flag.
         "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]


def find_chromium() -> str | None:
    for name in ("/usr/bin/chromium", "chromium", "chromium-browser"):
        path = shutil.which(name)
        if path:
            return path
    return None


class CDPError(RuntimeError):
    pass


class Chromium:
    def __init__(self, binary: str, profile: Path, size: tuple[int, int] = (1280, 900),
                 timeout: float = 30.0) -> None:
        profile.mkdir(parents=True, exist_ok=True)
        self.proc = subprocess.Popen(
            [binary, *FLAGS, f"--user-data-dir={profile}", f"--window-size={size[0]},{size[1]}",
             "--remote-debugging-address=127.0.0.1", "--remote-debugging-port=0", "about:blank"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
        self._id = 0
        self._ws = None
        try:
            port = self._devtools_port(profile / "DevToolsActivePort", timeout)
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=timeout) as resp:
                pages = [t for t in json.load(resp) if t.get("type") == "page"]
            if not pages:
                raise CDPError("chromium opened no page target")
            self._ws = connect(pages[0]["webSocketDebuggerUrl"], max_size=None, open_timeout=10)
            # headless --window-size includes no browser chrome but is not always honoured: pin the viewport
            self.call("Emulation.setDeviceMetricsOverride", width=size[0], height=size[1], deviceScaleFactor=1,
                      mobile=False)
        except BaseException:
            self.close()
            raise

    def _devtools_port(self, path: Path, timeout: float) -> int:
        deadline = time.time() + timeout
        while time.time() < deadline:
            if self.proc.poll() is not None:
                raise CDPError(f"chromium exited with {self.proc.returncode} before DevTools came up")
            if path.exists():
                text = path.read_text().split()
                if text:
                    return int(text[0])
            time.sleep(0.1)
        raise CDPError(f"chromium wrote no {path.name} within {timeout} s")

    def call(self, method: str, timeout: float = 30.0, **params: Any) -> dict:
        self._id += 1
        self._ws.send(json.dumps({"id": self._id, "method": method, "params": params}))
        deadline = time.time() + timeout
        while True:
            reply = json.loads(self._ws.recv(timeout=max(0.1, deadline - time.time())))
            if reply.get("id") == self._id:  # everything else is an event we did not ask for
                if "error" in reply:
                    raise CDPError(f"{method}: {reply['error']}")
                return reply.get("result", {})

    def pump(self, seconds: float) -> None:
        """Wait ``seconds``, reading (and dropping) the events that arrive meanwhile."""
        deadline = time.monotonic() + seconds
        while (left := deadline - time.monotonic()) > 0:
            try:
                self._ws.recv(timeout=left)
            except TimeoutError:
                return

    def navigate(self, url: str) -> None:
        self.call("Page.enable")
        self.call("Page.navigate", url=url)

    def evaluate(self, expression: str, timeout: float = 90.0, await_promise: bool = False) -> Any:
        # generous: a software-WebGL page on a busy 2-core machine can starve its main thread for a while
        result = self.call("Runtime.evaluate", timeout=timeout, expression=expression, returnByValue=True,
                           awaitPromise=await_promise)
        if "exceptionDetails" in result:
            raise CDPError(f"{expression!r} threw: {result['exceptionDetails'].get('text')}")
        return result["result"].get("value")

    def screenshot(self, path: Path, timeout: float = 90.0) -> Path:
        data = self.call("Page.captureScreenshot", timeout=timeout, format="png")["data"]
        path.write_bytes(base64.b64decode(data))
        return path

    def close(self) -> None:
        if self._ws is not None:
            try:
                self._ws.close()
            except Exception:
                pass
        if self.proc.poll() is None:
            try:
                os.killpg(self.proc.pid, signal.SIGTERM)
                self.proc.wait(10)
            except (ProcessLookupError, subprocess.TimeoutExpired):
                try:
                    os.killpg(self.proc.pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
                self.proc.wait()
