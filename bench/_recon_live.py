"""recon keeping up with camhub in a live ``xm up`` of deploy/sim.toml (bench/recon.py --live):
the deployment runs on a private router, run directory and panel port; after recon's first scene,
camhub's and recon's @health counters are read at the start and the end of the window. A frame
set camhub published and recon neither reconstructed nor still holds is dropped."""

from __future__ import annotations

import json
import os
import re
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import zenoh

from shared.process_group import stop_group
from shared.runtime import open_client

ROOT = Path(__file__).resolve().parents[1]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _health(router: str, selector: str) -> dict:
    try:
        session = open_client(router)
    except zenoh.ZError:
        return {}
    try:
        replies = [json.loads(r.ok.payload.to_bytes()) for r in session.get(selector, timeout=3.0) if r.ok]
    finally:
        session.close()
    return replies[0] if replies else {}


def _counters(router: str) -> dict:
    cam, rec = _health(router, "xm/camhub/main/@health"), _health(router, "xm/recon/main/@health")
    images = {k: v for k, v in cam.get("published", {}).items() if k.endswith("/image")}
    return {
        "t": time.monotonic(),
        "camhub_frame_sets": min(images.values()) if images else 0,
        "recon_frame_sets": rec.get("frame_sets", 0),
        "recon_scenes": rec.get("published", {}).get("xm/recon/main/scene", 0),
        "images_arrived": sum(v for k, v in rec.get("arrived", {}).items() if k.endswith("/image")),
        "images_dropped": sum(v for k, v in rec.get("dropped", {}).items() if k.endswith("/image")),
        "partial_frame_sets": rec.get("partial_frame_sets", 0),
        "late_images": rec.get("late_images", 0),
        "corrupt_jpeg": sum(v for k, v in rec.get("errors", {}).items() if k.startswith("corrupt_jpeg")),
        "image_without_info": sum(v for k, v in rec.get("errors", {}).items() if k.startswith("image_without_info")),
        "too_few_cameras": rec.get("errors", {}).get("too_few_cameras", 0),
        "hands_seen_twice": rec.get("hands_seen_twice", 0),
        "recon_status": rec.get("status"), "recon_detector": rec.get("detector"),
        "detector_precision": rec.get("detector_precision"), "stage_ms_median": rec.get("stage_ms_median", {}),
    }


def live(seconds: float, startup_timeout: float = 240.0) -> dict:
    with tempfile.TemporaryDirectory(prefix="xm-recon-live-") as tmp:
        router = f"tcp/127.0.0.1:{_free_port()}"
        text = (ROOT / "deploy" / "sim.toml").read_text()
        text = re.sub(r'router = "[^"]*"', f'router = "{router}"', text)
        text = re.sub(r'run_dir = "[^"]*"', f'run_dir = "{tmp}/run"', text)
        text = re.sub(r'checkpoint = "[^"]*"', f'checkpoint = "{tmp}/no-policy.pt"', text)
        text = re.sub(r'first_network = "[^"]*"', 'first_network = ""', text)  # no training job in the measurement
        text = re.sub(r"port = 8080", f"port = {_free_port()}", text)
        text = re.sub(r'directory = "[^"]*"', f'directory = "{tmp}/recordings"', text)
        deployment = Path(tmp) / "sim.toml"
        deployment.write_text(text)
        log = (Path(tmp) / "up.log").open("w")
        proc = subprocess.Popen([sys.executable, "-m", "shared.cli", "up", str(deployment), "--quiet"], cwd=ROOT,
                                stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        try:
            deadline = time.monotonic() + startup_timeout
            while _counters(router)["recon_scenes"] < 3:
                if time.monotonic() > deadline or proc.poll() is not None:
                    return {"error": "recon published no scene", "log": (Path(tmp) / "up.log").read_text()[-2000:]}
                time.sleep(1.0)
            start = _counters(router)
            load0 = os.getloadavg()
            time.sleep(seconds)  # the measurement window itself
            end = _counters(router)
            load1 = os.getloadavg()
        finally:
            stop_group(proc, 30)
            log.close()
    delta = {k: end[k] - start[k] for k in start if isinstance(start[k], int | float) and k != "t"}
    published, handled = delta["camhub_frame_sets"], delta["recon_frame_sets"]
    return {"seconds": round(end["t"] - start["t"], 1), "camhub_frame_sets": published, "recon_frame_sets": handled,
            "frame_sets_dropped": max(0, published - handled - 1),  # one may be in flight at the end
            "counters_delta": delta, "recon_status": end["recon_status"], "detector": end["recon_detector"],
            "detector_precision": end["detector_precision"], "recon_stage_ms_median": end["stage_ms_median"],
            "load_average_start_end": [round(v, 2) for v in (*load0[:1], *load1[:1])]}
