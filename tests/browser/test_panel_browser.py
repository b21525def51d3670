"""The dashboard in a real browser: headless Chromium (DevTools protocol) loads the panel, connects,
shows what was published, and its record button reaches the recorder. Screenshot: .cache/panel.png."""

from __future__ import annotations

import json
import shutil
import time

import cv2
import numpy as np
import pytest

from shared import msgs
from tests.browser._cdp import Chromium, find_chromium
from tests.conftest import ROOT, ServiceProcess, free_port, query_json, wait_for, wait_until, write_deployment
from tests.contract.test_panel_contract import camera_info, joint_state, plan, scene, tactile

CHROMIUM = find_chromium()
pytestmark = [pytest.mark.browser,
              pytest.mark.skipif(CHROMIUM is None, reason="needs /usr/bin/chromium (apt-get install chromium)")]

PAGE_TEXT = "document.body ? document.body.innerText : ''"


def session_msg() -> object:
    return msgs.make("xm_msgs/msg/Session", header=msgs.header(time.time()), task="pick_place", demo=3, phase="grasp",
                     tactile_hand="right", seed_layout="{}")


def jpeg() -> object:
    img = np.zeros((120, 160, 3), np.uint8)
    img[:, :80] = (0, 200, 0)
    data = cv2.imencode(".jpg", img)[1].tobytes()
    return msgs.make("sensor_msgs/msg/CompressedImage", header=msgs.header(time.time(), "cam0"), format="jpeg",
                     data=np.frombuffer(data, np.uint8))


def test_panel_renders_and_records_in_headless_chromium(router, tmp_path):
    endpoint, session = router
    port = free_port()
    dep = write_deployment(tmp_path / "d.toml", endpoint,
                           {"panel": {"main": {"port": port, "fps": 10.0, "health_period_s": 0.5}}})
    requests: list[dict] = []

    def fake_recorder(query) -> None:  # stands in for the recorder service
        payload = query.payload.to_bytes() if query.payload is not None else b""
        requests.append(json.loads(payload or b"{}"))
        query.reply(str(query.key_expr), json.dumps({"ok": True, "path": "/tmp/rec/test-0001.mcap"}))

    recorder = session.declare_queryable("xm/recorder/main/@cmd/start", fake_recorder)
    frames = {"xm/robot/workcell/state": joint_state(), "xm/recon/main/scene": scene(),
              "xm/glove/left/tactile": tactile("left"), "xm/glove/right/tactile": tactile("right"),
              "xm/camhub/cam0/info": camera_info(), "xm/camhub/cam0/image": jpeg(),
              "xm/world/sim/session": session_msg(), "xm/policy/main/plan": plan()}
    pubs = {k: (session.declare_publisher(k), m) for k, m in frames.items()}
    panel = ServiceProcess("panel", dep, "main", tmp_path / "panel.log")
    browser = None
    try:
        assert wait_for(lambda: query_json(session, "xm/panel/main/@health"), 30), panel.output()
        browser = Chromium(CHROMIUM, tmp_path / "profile")
        browser.navigate(f"http://127.0.0.1:{port}")

        def drawn() -> dict | None:
            for pub, msg in pubs.values():  # stamped now: the panel refuses stale stamps
                msg.header.stamp = msgs.stamp(time.time())
                pub.put(msgs.serialize(msg))
            rep = query_json(session, "xm/panel/main/@health")
            return rep[0] if rep and rep[0]["clients"] >= 1 and rep[0]["frames_drawn"] > 0 else None

        health = wait_for(drawn, 60, 0.3)
        assert health, f"the page never connected to viser: {query_json(session, 'xm/panel/main/@health')}"
        assert "cam0" in health["frustums"], "camera frustum not built from CameraInfo.p"
        assert browser.evaluate("document.querySelectorAll('canvas').length") >= 1, "no 3D canvas"
        assert browser.evaluate("!!document.createElement('canvas').getContext('webgl2')"), "no WebGL"
        text = wait_for(lambda: (t := browser.evaluate(PAGE_TEXT)) and "pick_place" in t and "panel/main" in t
                        and t, 30, 0.5)
        assert text, f"session and status table never shown; page text: {browser.evaluate(PAGE_TEXT)[:500]}"

        clicked = browser.evaluate(
            "(() => { const b = [...document.querySelectorAll('button')]"
            ".find(e => e.textContent.includes('Start recording')); if (b) b.click(); return !!b; })()")
        assert clicked, "no 'Start recording' button"
        assert wait_for(lambda: "test-0001.mcap" in browser.evaluate(PAGE_TEXT), 20, 0.3), \
            "the recorder's reply never appeared in the panel"
        assert requests == [{"keys": "xm/**"}]

        def drawn_screenshot():  # the software renderer takes a few frames to show everything
            shot = browser.screenshot(tmp_path / "panel.png")
            pixels = cv2.cvtColor(cv2.imread(str(shot)), cv2.COLOR_BGR2RGB).astype(float)
            viewport = pixels[150:-150, 300:900]  # the 3D view, clear of the GUI panel and notifications
            return shot if pixels.std() > 5.0 and (np.abs(viewport - 255).sum(axis=2) > 60).mean() > 0.01 else None

        shot = wait_until(drawn_screenshot, 20, "a screenshot that is not blank and draws the 3D view", period=0.5)
        (ROOT / ".cache").mkdir(exist_ok=True)
        shutil.copy(shot, ROOT / ".cache" / "panel.png")
        health = query_json(session, "xm/panel/main/@health")[0]
        assert "draw_error" not in health["errors"], panel.output()
    finally:
        if browser is not None:
            browser.close()
        recorder.undeclare()
        assert panel.stop() in (0, -15), panel.output()
