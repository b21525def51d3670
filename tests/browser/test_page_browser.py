"""The panel's page script in headless Chromium: a button pressed at once after a choice acts on the
new choice (and on the text typed before it), every time (services/panel/page.py). Without the
script viser's page drops the choice in about one press of ten this way."""

from __future__ import annotations

import pytest
import viser

from services.panel.page import hold_clicks
from tests.browser._cdp import Chromium, find_chromium
from tests.browser._page import WAIT, choose, click_button, type_into
from tests.conftest import free_port, wait_until

CHROMIUM = find_chromium()
pytestmark = [pytest.mark.browser,
              pytest.mark.skipif(CHROMIUM is None, reason="needs /usr/bin/chromium (apt-get install chromium)")]
ROUNDS = 20


@pytest.mark.timeout(600)
def test_a_press_follows_the_values_typed_and_chosen_just_before(tmp_path):
    server = viser.ViserServer(host="127.0.0.1", port=free_port(), verbose=False)
    hold_clicks(server)
    with server.gui.add_folder("Teaching session"):
        teacher = server.gui.add_text("teacher", initial_value="teacher")
        hand = server.gui.add_dropdown("glove hand", ("left", "right"), initial_value="right")
        pressed: list[tuple[str, str]] = []
        server.gui.add_button("Start session").on_click(lambda _e: pressed.append((teacher.value, hand.value)))
    browser = None
    try:
        browser = Chromium(CHROMIUM, tmp_path / "profile", size=(800, 600))
        browser.navigate(f"http://127.0.0.1:{server.get_port()}")
        for i in range(ROUNDS):
            want = (f"ada {i}", ("left", "right")[i % 2])
            type_into(browser, "teacher", want[0])
            # two changes within the page's 50 ms interval still lose the first (not what a hand does)
            wait_until(lambda w=want[0]: teacher.value == w, WAIT, f"the typed teacher {want[0]!r}")
            choose(browser, "glove hand", want[1])
            n = len(pressed)
            click_button(browser, "Start session")  # at once, as a script or a quick hand does
            wait_until(lambda n=n: len(pressed) > n, WAIT, f"press {i} reaching the server")
            assert pressed[-1] == want, f"press {i} acted on {pressed[-1]}, the page showed {want}"
    finally:
        if browser is not None:
            browser.close()
        server.stop()
