"""The live overview in a real browser (headless Chromium over the DevTools protocol), against the
real policy service serving a small trained network: a neural simulation from the live scene is
drawn as a ghost (the rendered 3-D view changes while the scene stands still), "follow the live
scene" keeps simulating as the scene moves, and alerts arrive as toasts: a glove losing frames, a
recording dropping messages, a service that stops answering and comes back (stand-in @health
replies). Screenshots: .cache/overview_neural_sim.png, .cache/overview_toasts.png."""

from __future__ import annotations

import json
import shutil
import threading
import time

import numpy as np
import pytest

from learning.ours import train
from learning.presets import preset
from services.world.teacher import generate_demo
from tests.browser._cdp import Chromium, find_chromium
from tests.browser._page import PATIENCE_S, WAIT, click_button, page_text, press, viewport
from tests.conftest import ROOT, ServiceProcess, free_port, query_json, wait_for, wait_until, write_deployment
from tests.contract.test_pipeline_services import _scene_msg

CHROMIUM = find_chromium()
pytestmark = [pytest.mark.browser,
              pytest.mark.skipif(CHROMIUM is None, reason="needs /usr/bin/chromium (apt-get install chromium)")]


def checkbox(label: str) -> str:
    return f"[...document.querySelectorAll('label')].find(l => l.textContent.trim() === {label!r})" \
           "?.closest('.mantine-Flex-root')?.querySelector('input[type=checkbox]')"


@pytest.mark.timeout(900)  # about 1 min on an idle host; software WebGL on a loaded host takes minutes
def test_neural_simulation_and_alerts_in_headless_chromium(router, tmp_path):
    endpoint, session = router
    demo = generate_demo("assembly", 11, index=0)
    train(preset("no_tactile", steps=20, hidden=(64, 64), batch=32, eval_every=10_000), [demo], None,
          tmp_path / "net", progress=False)
    port = free_port()
    dep = write_deployment(tmp_path / "d.toml", endpoint, {
        "policy": {"main": {"method": "learned", "checkpoint": str(tmp_path / "net" / "policy.pt"), "rate_hz": 2.0}},
        "panel": {"main": {"port": port, "fps": 10.0, "health_period_s": 1.0, "recordings": str(tmp_path / "rec"),
                           "models": str(tmp_path / "models")}}})
    frame = {"k": 10}  # the scene published: the demonstration's frame k (standing still until moved)
    stop = threading.Event()

    def feed() -> None:
        while not stop.wait(0.2):
            session.put("xm/recon/main/scene", _scene_msg(demo, frame["k"] % len(demo.hands), time.time()))

    glove = {"service": "glove", "instance": "left", "status": "ok", "decoder": {"frames_lost": 0},
             "published_hz": {"xm/glove/left/tactile": 100.0}}
    recorder = {"service": "recorder", "instance": "main", "status": "ok", "recording": True,
                "dropped": {"queue_overflow": 0}}
    answering = threading.Event()
    answering.set()

    def health(report: dict, query) -> None:
        if answering.is_set() or report is recorder:
            query.reply(f"xm/{report['service']}/{report['instance']}/@health", json.dumps(report))

    queryables = [session.declare_queryable(f"xm/{r['service']}/{r['instance']}/@health",
                                            lambda q, r=r: health(r, q)) for r in (glove, recorder)]
    policy = ServiceProcess("policy", dep, "main", tmp_path / "policy.log")
    panel = ServiceProcess("panel", dep, "main", tmp_path / "panel.log")
    feeder = threading.Thread(target=feed, daemon=True)
    browser = None

    def panel_health() -> dict:
        return query_json(session, "xm/panel/main/@health")[0]

    try:
        feeder.start()
        (ROOT / ".cache").mkdir(exist_ok=True)
        assert wait_for(lambda: query_json(session, "xm/panel/main/@health"), 90), panel.output()
        wait_until(lambda: (query_json(session, "xm/policy/main/@health") or [{}])[0].get("method", "").startswith(
            "learned"), 120, lambda: f"the network served: {policy.output()}")
        browser = Chromium(CHROMIUM, tmp_path / "profile", size=(1024, 800))
        browser.navigate(f"http://127.0.0.1:{port}")
        wait_until(lambda: "Neural simulation" in page_text(browser), WAIT, "the page loaded")
        before = wait_until(lambda: (s := browser.screenshot(tmp_path / "a.png", PATIENCE_S)) and
                            viewport(s).std() > 5 and s, WAIT, "a drawn 3D view")
        before_px = viewport(before)

        # a neural simulation from the live scene (standing still): only the ghost changes the view
        click_button(browser, "Simulate")
        wait_until(lambda: "from the live scene:" in page_text(browser), WAIT,
                   lambda: f"the rollout described; page: {page_text(browser)[-1500:]}\n{policy.output()[-2000:]}")
        shown = panel_health()["neural_sim"]
        assert shown["runs"] == 1 and shown["shown"]["policy"] == "no_tactile" and shown["shown"]["steps"] > 2

        def ghost_drawn():
            shot = browser.screenshot(tmp_path / "b.png", PATIENCE_S)
            return shot if np.abs(viewport(shot) - before_px).sum(axis=2).__gt__(60).mean() > 0.001 else None

        shutil.copy(wait_until(ghost_drawn, WAIT, "the ghost drawn in the 3D view", period=0.5),
                    ROOT / ".cache" / "overview_neural_sim.png")

        # follow the live scene: simulated again as the scene moves
        wait_until(lambda: press(browser, checkbox("follow the live scene")), WAIT, "the follow checkbox")
        runs = panel_health()["neural_sim"]["runs"]
        for k in (40, 80, 120):
            frame["k"] = k
            wait_until(lambda r=runs: panel_health()["neural_sim"]["runs"] > r, WAIT, "a rollout following the scene")
            runs = panel_health()["neural_sim"]["runs"]
        wait_until(lambda: press(browser, checkbox("follow the live scene")), WAIT, "the follow checkbox off")

        # alerts as toasts; the stand-in glove is in the service table: the panel has its baseline
        wait_until(lambda: "glove/left" in page_text(browser), WAIT,
                   lambda: f"the glove in the service table; page: {page_text(browser)[-1500:]}")
        glove["decoder"] = {"frames_lost": 9}
        recorder["dropped"] = {"queue_overflow": 4}
        wait_until(lambda: "glove/left: device gap" in page_text(browser), WAIT,
                   lambda: f"the device gap toast; page: {page_text(browser)[-1500:]}")
        assert "9 more frames lost (total 9)" in page_text(browser)
        wait_until(lambda: "recording dropped messages" in page_text(browser), WAIT, "the dropped recording toast")
        browser.screenshot(ROOT / ".cache" / "overview_toasts.png", PATIENCE_S)
        answering.clear()
        wait_until(lambda: "glove/left down" in page_text(browser), WAIT,
                   lambda: f"the service down toast; page: {page_text(browser)[-1500:]}")
        answering.set()
        wait_until(lambda: "glove/left back" in page_text(browser), WAIT, "the service back toast")
        health = panel_health()
        assert {"glove/left: device gap", "recording dropped messages", "glove/left down",
                "glove/left back"} <= {a["title"] for a in health["alerts"]}, health["alerts"]
        assert not {k for k in health["errors"] if k.startswith(("draw_error", "neural_sim_error", "toast_error"))}, \
            health["errors"]
    finally:
        stop.set()
        feeder.join(5)
        if browser is not None:
            browser.close()
        for q in queryables:
            q.undeclare()
        policy.stop()
        assert panel.stop() in (0, -15), panel.output()
