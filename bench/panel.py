"""The dashboard stays responsive while a network trains: scene redraws per second in the browser.

A panel (its own process, ``--fps`` draws a second while a browser is connected) gets moving hands
and objects published at 30 Hz through a private router; headless Chromium (software WebGL) shows
it. Measured through the DevTools protocol, per second: the frames in which the 3-D scene was
rendered (a WebGL clear of the page's canvas, counted by a script the protocol installs before the
page loads), the
animation frames the page produced (requestAnimationFrame); and the panel's own draws per second
(its @health ``frames_drawn``). Two phases in the same run: ``--seconds`` with the cell's
stand-in alone (the baseline), then as long again while `xm train` (the code path of the page's
Train, ``--threads`` torch threads) trains the first network beside it. Reports medians and the
ratio training / alone; writes .bench/panel.json. Target: scene redraw >= 15 per second while the
job trains. Run it under ``nice -n 19`` on a shared host; figures on a loaded host are noisy.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # runnable as a script from anywhere

from services.panel.service import PanelService  # noqa: E402
from services.world.teacher import generate_demo  # noqa: E402
from shared.realtime import shift_autogroup  # noqa: E402
from shared.runtime import open_router  # noqa: E402
from tests.browser._cdp import Chromium, find_chromium  # noqa: E402
from tests.conftest import (  # noqa: E402
    ServiceProcess,
    free_endpoint,
    free_port,
    query_json,
    wait_until,
    write_deployment,
)
from tests.contract.test_pipeline_services import _scene_msg  # noqa: E402

TARGET_FPS = 15.0
SCENE_HZ = 30.0
# Installed before any page script: counts the animation frames the page produced, those in which
# the 3-D scene was rendered (a WebGL clear: three.js clears its canvas at every render, several
# times for shadows).
COUNTERS = """
window.__renders = 0; window.__frames = 0; window.__drew = false;
for (const C of [window.WebGLRenderingContext, window.WebGL2RenderingContext]) {
  if (!C) continue;
  const clear = C.prototype.clear;
  C.prototype.clear = function (...a) { window.__drew = true; return clear.apply(this, a); };
}
(function tick() {
  window.__frames++;
  if (window.__drew) { window.__renders++; window.__drew = false; }
  requestAnimationFrame(tick);
})();
"""
READ = "[window.__renders, window.__frames]"


def publish_scenes(session, stop: threading.Event) -> None:
    """A teacher demonstration's scenes, looped at 30 Hz: every draw has moved hands and objects."""
    demo = generate_demo("assembly", 11, index=0)
    pub = session.declare_publisher("xm/recon/main/scene")
    k, period = 0, 1.0 / SCENE_HZ
    next_t = time.monotonic()
    while not stop.is_set():
        pub.put(_scene_msg(demo, k % len(demo.hands), time.time()))
        k += 1
        next_t += period
        time.sleep(max(0.0, next_t - time.monotonic()))


def frames_drawn(session) -> int:
    return int(query_json(session, "xm/panel/main/@health", timeout=5.0)[0]["frames_drawn"])


def measure(browser: Chromium, session, seconds: float) -> dict:
    """Per-second counts over ``seconds``: renders and animation frames in the page; the panel's draws."""
    renders, frames = [], []
    drawn0, t0 = frames_drawn(session), time.monotonic()
    last = browser.evaluate(READ)
    t_last = time.monotonic()
    end = t_last + seconds
    while time.monotonic() < end:
        browser.pump(1.0)
        now_counts, now = browser.evaluate(READ), time.monotonic()
        dt = now - t_last
        renders.append((now_counts[0] - last[0]) / dt)
        frames.append((now_counts[1] - last[1]) / dt)
        last, t_last = now_counts, now
    out = {name: {"median": round(statistics.median(v), 2), "min": round(min(v), 2), "samples": len(v)}
           for name, v in (("scene_renders_per_s", renders), ("animation_frames_per_s", frames))}
    out["panel_draws_per_s"] = round((frames_drawn(session) - drawn0) / (time.monotonic() - t0), 2)
    return out


def start_training(out: Path, threads: int) -> tuple[subprocess.Popen, Path]:
    """`xm train --teacher 0` as the dashboard's first-network job runs it, with a budget it will not finish."""
    progress = out / "progress.jsonl"
    out.mkdir(parents=True)
    proc = subprocess.Popen([sys.executable, "-m", "shared.cli", "train", "--teacher", "0", "--preset", "no_tactile",
                             "--threads", str(threads), "--steps", "2000", "--out", str(out), "--progress",
                             str(progress)], cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)
    shift_autogroup(proc.pid, -PanelService.Params().train_share)  # the share the page gives its jobs
    return proc, progress


def steps_done(progress: Path) -> int:
    try:
        lines = progress.read_text().splitlines()
    except OSError:
        return 0
    return max((json.loads(ln).get("step", 0) for ln in lines if ln.strip()), default=0)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seconds", type=float, default=30.0, help="length of each phase")
    parser.add_argument("--fps", type=float, default=15.0, help="the panel's draw rate (its `fps` parameter)")
    parser.add_argument("--threads", type=int, default=PanelService.Params().train_threads,
                        help="torch threads of the training job (default: the panel's train_threads, %(default)s)")
    args = parser.parse_args(argv)
    chromium = find_chromium()
    if chromium is None:
        print("needs /usr/bin/chromium (apt-get install chromium)", file=sys.stderr)
        return 2
    endpoint = free_endpoint()
    session = open_router(endpoint)
    stop = threading.Event()
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        port = free_port()
        dep = write_deployment(tmp / "d.toml", endpoint, {"panel": {"main": {
            "port": port, "fps": args.fps, "recordings": str(tmp / "recordings"), "models": str(tmp / "models")}}})
        panel = ServiceProcess("panel", dep, "main", tmp / "panel.log")
        feeder = threading.Thread(target=publish_scenes, args=(session, stop), daemon=True)
        browser = training = None
        try:
            feeder.start()
            browser = Chromium(chromium, tmp / "profile", size=(1024, 800))
            browser.call("Page.addScriptToEvaluateOnNewDocument", source=COUNTERS)
            wait_until(lambda: panel.alive() and _serving(port), 120, panel.output)
            browser.navigate(f"http://127.0.0.1:{port}")
            wait_until(lambda: (browser.evaluate(READ) or [0])[0] > 10, 180, "the page rendering its scene")
            browser.pump(3.0)  # the page settled
            alone = measure(browser, session, args.seconds)
            print(f"alone:    {json.dumps(alone)}")
            training, progress = start_training(tmp / "train", args.threads)
            # measured once it trains (its first report, step 10): not while it imports and makes its demonstrations
            wait_until(lambda: steps_done(progress) > 0 or training.poll() is not None, 600, "the job training")
            step0, t0 = steps_done(progress), time.monotonic()
            beside = measure(browser, session, args.seconds)
            if training.poll() is not None:
                raise SystemExit(f"the training job exited ({training.returncode}) during the measurement")
            rate = (steps_done(progress) - step0) / (time.monotonic() - t0)
            print(f"training: {json.dumps(beside)} ({rate:.1f} steps/s as reported every 10 steps)")
        finally:
            stop.set()
            if training is not None and training.poll() is None:
                training.kill()
                training.wait()
            if browser is not None:
                browser.close()
            panel.stop()
            session.close()
    ratio = beside["scene_renders_per_s"]["median"] / max(alone["scene_renders_per_s"]["median"], 1e-9)
    met = beside["scene_renders_per_s"]["median"] >= TARGET_FPS
    res = {"target": {"scene_renders_per_s_while_training": TARGET_FPS}, "met": met, "panel_fps": args.fps,
           "scene_hz": SCENE_HZ, "train_threads": args.threads, "seconds_per_phase": args.seconds,
           "alone": alone, "training": beside, "training_reported_steps_per_s": round(rate, 2),
           "ratio_training_over_alone": round(ratio, 3), "host_load_1min": round(_load(), 2),
           "note": "headless Chromium, software WebGL (SwiftShader) on the same host as the panel and the job"}
    (ROOT / ".bench").mkdir(exist_ok=True)
    (ROOT / ".bench/panel.json").write_text(json.dumps(res, indent=2))
    print(f"scene redraw while training: median {beside['scene_renders_per_s']['median']:.1f}/s "
          f"(alone {alone['scene_renders_per_s']['median']:.1f}/s, ratio {ratio:.2f}); target >= {TARGET_FPS:g}: "
          f"{'met' if met else 'NOT met'}")
    return 0


def _serving(port: int) -> bool:
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=2):
            return True
    except OSError:
        return False


def _load() -> float:
    return float(Path("/proc/loadavg").read_text().split()[0])


if __name__ == "__main__":
    raise SystemExit(main())
