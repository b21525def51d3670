"""The dashboard in a real browser: headless Chromium (DevTools protocol) loads the panel, connects,
shows what was published, its record button reaches the recorder, and the tactile map shows on the
gloved hand. Screenshots: .cache/panel.png, .cache/panel_tactile.png."""

from __future__ import annotations

import json
import shutil
import threading
import time

import cv2
import numpy as np
import pytest

from shared import msgs
from tests.browser._cdp import Chromium, find_chromium
from tests.conftest import ROOT, ServiceProcess, free_port, query_json, wait_for, wait_until, write_deployment
from tests.contract.test_panel_contract import camera_info, joint_state, plan, scene, tactile, tactile_mesh

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


def click(browser: Chromium, label: str) -> bool:
    return browser.evaluate("(() => { const b = [...document.querySelectorAll('button')]"
                            f".find(e => e.textContent.includes({label!r})); if (b) b.click(); return !!b; }})()")


def hot_pixels(shot) -> int:
    """Pixels in the tactile map's upper range (inferno's yellows: 27 kPa is (246, 215, 70), shaded
    darker) in the 3D view, clear of the notification and the axes widget; nothing else in the test
    scene has that colour (the left hand's salmon has far less green than red)."""
    rgb = cv2.cvtColor(cv2.imread(str(shot)), cv2.COLOR_BGR2RGB).astype(int)[150:800, 100:900]
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    return int(((r > 150) & (g > 120) & (r - g < 60) & (b < g - 50)).sum())


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
              "xm/world/sim/session": session_msg(), "xm/policy/main/plan": plan(),
              "xm/recon/main/tactile_mesh": tactile_mesh()}
    pubs = {k: (session.declare_publisher(k), m) for k, m in frames.items()}
    stop = threading.Event()

    def feed() -> None:  # every message at 5 Hz, stamped now (the panel refuses stale stamps), like a live cell
        while not stop.wait(0.2):
            for pub, msg in pubs.values():
                msg.header.stamp = msgs.stamp(time.time())
                pub.put(msgs.serialize(msg))

    feeder = threading.Thread(target=feed, daemon=True)
    panel = ServiceProcess("panel", dep, "main", tmp_path / "panel.log")
    browser = None
    try:
        feeder.start()
        assert wait_for(lambda: query_json(session, "xm/panel/main/@health"), 30), panel.output()
        browser = Chromium(CHROMIUM, tmp_path / "profile")
        browser.navigate(f"http://127.0.0.1:{port}")

        def drawn() -> dict | None:
            rep = query_json(session, "xm/panel/main/@health")
            return rep[0] if rep and rep[0]["clients"] >= 1 and rep[0]["frames_drawn"] > 0 else None

        health = wait_for(drawn, 60, 0.3)
        assert health, f"the page never connected to viser: {query_json(session, 'xm/panel/main/@health')}"
        assert "cam0" in health["frustums"], "camera frustum not built from CameraInfo.p"
        assert wait_for(lambda: (h := drawn()) and h["tactile_meshes"] == ["right"], 20, 0.3), "no tactile mesh"
        assert browser.evaluate("document.querySelectorAll('canvas').length") >= 1, "no 3D canvas"
        assert browser.evaluate("!!document.createElement('canvas').getContext('webgl2')"), "no WebGL"
        text = wait_for(lambda: (t := browser.evaluate(PAGE_TEXT)) and "pick_place" in t and "panel/main" in t
                        and t, 30, 0.5)
        assert text, f"session and status table never shown; page text: {browser.evaluate(PAGE_TEXT)[:500]}"

        assert click(browser, "Start recording"), "no 'Start recording' button"
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

        assert click(browser, "Look at the gloved hand"), "no 'Look at the gloved hand' button"

        def tactile_screenshot():  # the pressed thumb and index, close up (the GLB takes a while to load)
            shot = browser.screenshot(tmp_path / "panel_tactile.png")
            return shot if hot_pixels(shot) > 300 else None

        shot = wait_until(tactile_screenshot, 90, lambda: f"the pressed fingertips drawn in the tactile map's "
                          f"colours ({hot_pixels(tmp_path / 'panel_tactile.png')} pixels)", period=1.0)
        shutil.copy(shot, ROOT / ".cache" / "panel_tactile.png")
        health = query_json(session, "xm/panel/main/@health")[0]
        assert "draw_error" not in health["errors"], panel.output()
    finally:
        stop.set()
        feeder.join(5)
        if browser is not None:
            browser.close()
        recorder.undeclare()
        assert panel.stop() in (0, -15), panel.output()
