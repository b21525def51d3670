"""A script the panel adds to viser's page: a button press is sent after the page's pending changes.

viser's page (1.1.1) sends every change of the GUI (a typed character, a dropdown choice, a button
press) through one sender that lets one message through per 50 ms and keeps only the newest one
held back: a press within 50 ms of two changes replaces the held change, which is never sent, so
the server acts on the old value of that field (and keeps it). The script catches each click on a
button before the page does and dispatches it again 60 ms later: by then the sender's 50 ms timer,
armed earlier, has sent the held change (timers fire in deadline order, however late), so the
press follows every change made before it.
"""

from __future__ import annotations

import viser
from viser import _messages

HOLD_MS = 60  # above the page's 50 ms send interval

HOLD_CLICKS_JS = """
if (!window.__xmHeldClicks) {
  const held = new WeakSet();
  window.__xmHeldClicks = held;
  window.addEventListener("click", (e) => {
    const target = e.target;
    if (held.has(e) || !(target instanceof Element) || !target.closest("button")) return;
    e.stopImmediatePropagation();
    e.preventDefault();
    const init = {bubbles: true, cancelable: true, composed: true, view: window, detail: e.detail,
                  screenX: e.screenX, screenY: e.screenY, clientX: e.clientX, clientY: e.clientY,
                  ctrlKey: e.ctrlKey, shiftKey: e.shiftKey, altKey: e.altKey, metaKey: e.metaKey,
                  button: e.button, buttons: e.buttons};
    setTimeout(() => {
      const again = new MouseEvent("click", init);
      held.add(again);
      target.dispatchEvent(again);
    }, HOLD_MS);
  }, true);
}
""".replace("HOLD_MS", str(HOLD_MS))


def hold_clicks(server: viser.ViserServer) -> None:
    """Add the script to the page of every browser, present and future (the message stays in the
    server's persistent state, as viser's own plotly script does)."""
    # viser has no public call for a page script; this is the message its add_plotly sends
    server.gui._websock_interface.queue_message(_messages.RunJavascriptMessage(source=HOLD_CLICKS_JS))
