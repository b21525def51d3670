"""Driving viser's page in headless Chromium as a user does: labelled fields, dropdowns, buttons and
sliders found by their text, mouse and input events dispatched from the page's JavaScript."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from tests.browser._cdp import Chromium
from tests.conftest import wait_until

PAGE_TEXT = "document.body ? document.body.innerText : ''"
WAIT = 180  # seconds for anything the page shows: tens of seconds per DevTools call on a loaded host
PATIENCE_S = 240.0  # one DevTools call: software WebGL on a loaded 2-core host may hold the page that long
LABEL = "[...document.querySelectorAll('label')]"
ROW = f"(l) => {LABEL}.find(e => e.textContent.trim() === l)?.closest('.mantine-Flex-root')"

# Mouse events are dispatched from the page's JavaScript: the DevTools Input domain waits for the
# renderer to take the event, over 90 s on a loaded 2-core host with software WebGL.
PRESS = """(el) => {{ if (!el) return false; el.scrollIntoView({{block: 'center'}});
  const r = el.getBoundingClientRect();
  const o = {{bubbles: true, cancelable: true, view: window, button: 0, buttons: 1,
             clientX: r.x + r.width / 2, clientY: r.y + r.height / 2}};
  for (const [T, kind] of [[PointerEvent, 'pointerdown'], [MouseEvent, 'mousedown'], [PointerEvent, 'pointerup'],
                           [MouseEvent, 'mouseup'], [MouseEvent, 'click']]) el.dispatchEvent(new T(kind, o));
  return true; }}"""


# viser's page sends GUI changes through one sender that holds back what comes within 50 ms of its
# last message and then sends only the newest, so a change made inside that window erases the one
# held (services/panel/page.py covers a button press; nothing covers two fields). A page timer set
# now fires after viser's pending one (timers run in order of expiry, however late), so once it has
# fired the held change is on the wire. Each field change waits for that first, as a hand moving
# from one field to the next does.
SENT = "new Promise(done => setTimeout(() => done(true), 60))"


def sent(browser: Chromium) -> None:
    """Wait until the page has handed the GUI changes made so far to the websocket."""
    browser.evaluate(SENT, PATIENCE_S, await_promise=True)


def press(browser: Chromium, element_js: str) -> bool:
    """Press and release the mouse on the element ``element_js`` evaluates to; False if there is none."""
    return browser.evaluate(f"({PRESS.format()})({element_js})", PATIENCE_S)


def button(text: str) -> str:
    return f"[...document.querySelectorAll('button')].find(b => b.textContent.trim() === {text!r})"


def click_button(browser: Chromium, text: str) -> None:
    wait_until(lambda: press(browser, button(text)), WAIT, f"a button {text!r}")


def field(label: str) -> str:
    return f"({ROW})({label!r})?.querySelector('input:not([type=hidden])')"


def type_into(browser: Chromium, label: str, text: str) -> None:
    """Replace the text of the field labelled ``label`` as typing does (React hears an input event)."""
    sent(browser)
    wait_until(lambda: browser.evaluate(f"!!{field(label)}", PATIENCE_S), WAIT, f"a field labelled {label!r}")
    browser.evaluate(f"(() => {{ const e = {field(label)}; e.focus(); Object.getOwnPropertyDescriptor("
                     f"HTMLInputElement.prototype, 'value').set.call(e, {text!r}); "
                     "e.dispatchEvent(new Event('input', {bubbles: true})); })()", PATIENCE_S)


def choose(browser: Chromium, label: str, option: str) -> None:
    """Open the dropdown labelled ``label`` and click ``option`` in its list."""
    sent(browser)
    wait_until(lambda: press(browser, field(label)), WAIT, f"a dropdown labelled {label!r}")
    wait_until(lambda: press(browser, f"[...document.querySelectorAll('[role=option]')].find(o => "
                                      f"o.textContent.trim() === {option!r})"), WAIT, f"option {option!r} of {label!r}")
    wait_until(lambda: browser.evaluate(f"{field(label)}.value", PATIENCE_S) == option, WAIT,
               f"{label!r} showing {option!r}")


def key(browser: Chromium, label: str, name: str) -> None:
    """A key pressed on the slider labelled ``label`` (Home, End, ArrowLeft, ...), as the keyboard does."""
    sent(browser)
    thumb = f"({ROW})({label!r})?.querySelector('[role=slider]')"
    wait_until(lambda: browser.evaluate(f"(() => {{ const e = {thumb}; if (!e) return false; e.dispatchEvent("
                                        f"new KeyboardEvent('keydown', {{key: {name!r}, code: {name!r}, bubbles: true, "
                                        "cancelable: true})); return true; })()", PATIENCE_S), WAIT,
               f"the slider labelled {label!r}")


def value_of(browser: Chromium, label: str) -> str:
    return browser.evaluate(f"{field(label)}?.value ?? ''", PATIENCE_S)


def page_text(browser: Chromium) -> str:
    return browser.evaluate(PAGE_TEXT, PATIENCE_S)


def viewport(shot: Path) -> np.ndarray:
    """The 3D view, clear of the GUI panel on the right and the notifications."""
    return cv2.imread(str(shot)).astype(float)[150:-150, 100:600]
