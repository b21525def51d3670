"""The dashboard in a real browser: headless Chromium loads the panel, connects, and draws."""

from __future__ import annotations

import shutil
import subprocess
import time

import numpy as np
import pytest

from shared import msgs
from tests.conftest import ROOT, ServiceProcess, free_port, query_json, wait_for, write_deployment

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
pytestmark = [pytest.mark.browser,
              pytest.mark.skipif(CHROMIUM is None, reason="needs Debian chromium (apt-get install chromium)")]


def test_panel_renders_scene_in_headless_chromium(router, tmp_path):
    endpoint, session = router
    port = free_port()
    deployment = write_deployment(tmp_path / "d.toml", endpoint, {"panel": {"main": {"port": port, "fps": 10.0}}})
    panel = ServiceProcess("panel", deployment, "main", tmp_path / "panel.log")
    try:
        assert wait_for(lambda: query_json(session, "xm/panel/main/@health"), 30), panel.output()
        pub = session.declare_publisher("xm/robot/workcell/state")
        from shared.kinematics import load_robot

        names = load_robot("workcell").joint_names
        state = msgs.make("sensor_msgs/msg/JointState", header=msgs.header(time.time()), name=names,
                          position=np.full(len(names), 0.1), velocity=np.zeros(len(names)),
                          effort=np.zeros(len(names)))
        shot = tmp_path / "panel.png"
        browser = subprocess.Popen(
            [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
             "--disable-component-update", "--disable-sync", "--no-first-run", "--disable-quic",
             "--use-angle=swiftshader", "--enable-unsafe-swiftshader", f"--user-data-dir={tmp_path / 'profile'}",
             "--window-size=1280,800", "--virtual-time-budget=15000", f"--screenshot={shot}",
             f"http://127.0.0.1:{port}"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        clients = 0
        deadline = time.time() + 60
        while browser.poll() is None and time.time() < deadline:
            pub.put(msgs.serialize(state))
            health = query_json(session, "xm/panel/main/@health")
            clients = max(clients, health[0]["clients"] if health else 0)
            time.sleep(0.3)
        browser.wait(30)
        assert clients >= 1, "the page never opened a viser connection"
        health = query_json(session, "xm/panel/main/@health")[0]
        assert health["received_hz"].get("xm/robot/workcell/state", 0) > 0
        assert health["frames_drawn"] > 0, "the panel never drew for the connected browser"
        assert shot.exists(), "chromium wrote no screenshot"
        from PIL import Image

        pixels = np.asarray(Image.open(shot).convert("RGB"), float)
        assert pixels.std() > 5.0, "screenshot is blank"
        (ROOT / ".cache").mkdir(exist_ok=True)
        shutil.copy(shot, ROOT / ".cache" / "panel.png")
    finally:
        assert panel.stop() in (0, -15), panel.output()
