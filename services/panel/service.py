"""panel node: the viser dashboard at http://127.0.0.1:<port>.

Subscriptions keep the latest message per key; a render loop draws at ``fps`` from that state,
never per message. GUI callbacks run on viser's threads and only talk Zenoh (queries), so they
never touch the event loop's state.
"""

from __future__ import annotations

import asyncio
import json
import socket
import time
from dataclasses import dataclass

import cv2
import numpy as np
import viser

from services.panel import view
from shared import msgs
from shared.geometry import pose_from_projection, wxyz
from shared.keys import CAMERAS, GLOVES
from shared.kinematics import load_robot
from shared.runtime import EndpointError, Node, latest

HEALTH_PERIOD_S = 2.0


class PanelService:
    @dataclass
    class Params:
        port: int = 8080
        host: str = "127.0.0.1"
        fps: float = 15.0
        camera: str = "cam0"

    def __init__(self, node: Node, params: Params) -> None:
        self.node = node
        self.p = params
        _check_port(params.host, params.port)
        self.robot = load_robot("workcell")
        self.latest: dict[str, object] = {}
        self.camera_choice = params.camera
        self.server = viser.ViserServer(host=params.host, port=params.port, verbose=False)
        self.server.scene.set_up_direction("+z")
        self.server.initial_camera.position = (1.1, -0.9, 0.9)
        self.server.initial_camera.look_at = (0.0, 0.0, 0.15)
        self.server.initial_camera.up = (0.0, 0.0, 1.0)
        self._build_scene()
        self._build_gui()
        for key in ("xm/robot/workcell/state", "xm/recon/main/scene", "xm/policy/main/plan",
                    "xm/world/sim/session"):
            node.subscribe(key, self._keep, latest(1))
        node.subscribe("xm/glove/*/tactile", self._keep, latest(len(GLOVES)))
        node.subscribe("xm/camhub/*/info", self._keep, latest(len(CAMERAS)))
        node.subscribe("xm/camhub/*/image", self._keep_image, latest(len(CAMERAS)))
        self.frames_drawn = 0
        node.health_extra = lambda: {"clients": len(self.server.get_clients()), "url": self.url,
                                     "frames_drawn": self.frames_drawn}

    @property
    def url(self) -> str:
        return f"http://{self.p.host}:{self.p.port}"

    def _keep(self, msg, key: str) -> None:
        self.latest[key] = msg

    def _keep_image(self, msg, key: str) -> None:
        if key.split("/")[2] == self.camera_choice:
            self.latest["image"] = msg

    # --- layout -------------------------------------------------------------------------
    def _build_scene(self) -> None:
        sc = self.server.scene
        sc.add_grid("/table", width=0.8, height=0.8, cell_size=0.1, section_size=0.4, plane="xy")
        for x in (-0.4, 0.4):
            for y in (-0.4, 0.4):
                sc.add_box(f"/frame/post_{x}_{y}", color=(80, 80, 80), dimensions=(0.02, 0.02, 0.8),
                           position=(x, y, 0.4))
        self.links = {}
        for name, dims, _pose in view.link_boxes(self.robot, np.zeros(len(self.robot.joint_names))):
            self.links[name] = sc.add_box(f"/robot/{name}", color=(180, 185, 195), dimensions=tuple(dims))
        self.hand_handles = {h: sc.add_line_segments(f"/hands/{h}", np.zeros((20, 2, 3)),
                                                     np.zeros((20, 2, 3), np.uint8), thickness=0.006)
                             for h in GLOVES}
        self.objects = sc.add_point_cloud("/objects", np.zeros((1, 3)), np.zeros((1, 3), np.uint8), point_size=0.006,
                                          point_shape="circle")
        self.plan = sc.add_point_cloud("/plan", np.zeros((1, 3)), np.zeros((1, 3), np.uint8), point_size=0.003,
                                       point_shape="circle")
        self.frustums: dict[str, object] = {}

    def _build_gui(self) -> None:
        gui = self.server.gui
        self.session_md = gui.add_markdown("**session**: waiting for the world")
        with gui.add_folder("Tactile"):
            blank = view.tactile_image(np.zeros(256))
            self.tactile_images = {h: gui.add_image(blank, label=f"{h} glove") for h in GLOVES}
        with gui.add_folder("Camera"):
            dropdown = gui.add_dropdown("camera", list(CAMERAS), initial_value=self.camera_choice)
            dropdown.on_update(lambda _e: setattr(self, "camera_choice", dropdown.value))
            self.camera_image = gui.add_image(np.zeros((120, 160, 3), np.uint8), label="view")
        with gui.add_folder("Recording"):
            start = gui.add_button("Start recording", color="red")
            stop = gui.add_button("Stop recording")
            self.record_md = gui.add_markdown("not recording")
            start.on_click(lambda _e: self._recorder("start", {"keys": "xm/**"}))
            stop.on_click(lambda _e: self._recorder("stop", {}))
        with gui.add_folder("Services"):
            self.status_md = gui.add_markdown("querying...")

    def _recorder(self, verb: str, request: dict) -> None:  # viser thread: blocking query is fine here
        replies = [json.loads(r.ok.payload.to_bytes()) for r in self.node.session.get(
            f"xm/recorder/main/@cmd/{verb}", payload=json.dumps(request), timeout=3.0) if r.ok is not None]
        if not replies:
            self.record_md.content = "**error**: no recorder answered (is the recorder service running?)"
            return
        reply = replies[0]
        if not reply.get("ok"):
            self.record_md.content = f"**error**: {reply.get('error')}"
        elif verb == "start":
            self.record_md.content = f"recording to `{reply['path']}`"
        else:
            total = sum(reply.get("messages", {}).values())
            self.record_md.content = f"saved `{reply['path']}`: {total} messages, {reply.get('bytes', 0) / 1e6:.1f} MB"

    # --- loops --------------------------------------------------------------------------
    async def run(self) -> None:
        self.node.spawn(self._status_loop(), name="status")
        period = 1.0 / self.p.fps
        while True:
            t0 = time.monotonic()
            if not self.server.get_clients():  # nobody watching: keep only the latest state
                await asyncio.sleep(period)
                continue
            try:
                self._draw()
                self.frames_drawn += 1
            except Exception as exc:  # a bad message must not stop the dashboard
                self.node.stats.count("draw_error")
                self.node.log.warning("draw failed: %r", exc)
            await asyncio.sleep(max(0.0, period - (time.monotonic() - t0)))

    def _draw(self) -> None:
        state = self.latest.get("xm/robot/workcell/state")
        if state is not None:
            order = {n: i for i, n in enumerate(state.name)}
            q = np.array([state.position[order[n]] if n in order else 0.0 for n in self.robot.joint_names])
            for name, _dims, pose in view.link_boxes(self.robot, q):
                handle = self.links[name]
                handle.position = pose[:3, 3]
                handle.wxyz = wxyz(pose[:3, :3])
        scene = self.latest.pop("xm/recon/main/scene", None)
        if scene is not None:
            hands = np.asarray(scene.hand_keypoints, float).reshape(-1, 21, 3)
            masks = np.asarray(scene.hand_mask).reshape(-1, 21)
            for i, name in enumerate(scene.hand_names):
                if name in self.hand_handles:
                    seg, bright = view.hand_segments(hands[i], masks[i])
                    h = self.hand_handles[name]
                    h.points = seg
                    h.colors = view.segment_colors(view.HAND_COLORS[name], bright)
            pts = np.asarray(scene.object_keypoints, float).reshape(-1, 3)
            if len(pts):
                self.objects.points = pts.astype(np.float32)
                self.objects.colors = view.object_colors(list(scene.object_names))
        plan = self.latest.pop("xm/policy/main/plan", None)
        if plan is not None and len(plan.positions):
            pts = np.asarray(plan.positions, np.float32).reshape(-1, 3)
            self.plan.points = pts
            self.plan.colors = np.tile(np.array([[60, 200, 90]], np.uint8), (len(pts), 1))
        for hand in GLOVES:
            msg = self.latest.pop(f"xm/glove/{hand}/tactile", None)
            if msg is not None:
                self.tactile_images[hand].image = view.tactile_image(msg.pressure, msg.mask)
        for cam in CAMERAS:
            info = self.latest.pop(f"xm/camhub/{cam}/info", None)
            if info is not None and cam not in self.frustums:
                K, T = pose_from_projection(np.asarray(info.p))
                fov = 2 * np.arctan(info.height / (2 * K[1, 1]))
                self.frustums[cam] = self.server.scene.add_camera_frustum(
                    f"/cameras/{cam}", fov=float(fov), aspect=info.width / info.height, scale=0.05,
                    wxyz=wxyz(T[:3, :3]), position=T[:3, 3], color=(40, 40, 40), thickness=0.002)
        image = self.latest.pop("image", None)
        if image is not None:
            rgb = cv2.imdecode(np.frombuffer(bytes(image.data), np.uint8), cv2.IMREAD_COLOR)
            if rgb is not None:
                self.camera_image.image = cv2.cvtColor(rgb, cv2.COLOR_BGR2RGB)
        session = self.latest.pop("xm/world/sim/session", None)
        if session is not None:
            self.session_md.content = (f"**{session.task}** demo {session.demo}, phase **{session.phase}**, "
                                       f"glove on the {session.tactile_hand} hand, t = "
                                       f"{msgs.stamp_seconds(session.header.stamp):.1f} s")

    async def _status_loop(self) -> None:
        while True:
            if not self.server.get_clients():
                await asyncio.sleep(HEALTH_PERIOD_S)
                continue
            reports = await asyncio.to_thread(self._query_health)
            rows = ["| service | status | pid | up (s) | Hz | errors |", "|---|---|---|---|---|---|"]
            for r in sorted(reports, key=lambda r: (r.get("service", ""), r.get("instance", ""))):
                hz = ", ".join(f"{k.split('/')[-1]} {v:g}" for k, v in r.get("published_hz", {}).items())
                errs = ", ".join(f"{k} {v}" for k, v in r.get("errors", {}).items()) or "-"
                rows.append(f"| {r.get('service')}/{r.get('instance')} | {r.get('status')} | {r.get('pid')} | "
                            f"{r.get('uptime_s', 0):.0f} | {hz or '-'} | {errs} |")
            self.status_md.content = "\n".join(rows)
            await asyncio.sleep(HEALTH_PERIOD_S)

    def _query_health(self) -> list[dict]:
        out = []
        for reply in self.node.session.get("xm/**/@health", timeout=1.5):
            if reply.ok is not None:
                try:
                    out.append(json.loads(reply.ok.payload.to_bytes()))
                except ValueError:
                    self.node.stats.count("bad_health_reply")
        return out

    async def close(self) -> None:
        self.server.stop()


def _check_port(host: str, port: int) -> None:
    with socket.socket() as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind((host, port))
        except OSError as exc:
            raise EndpointError(f"panel: cannot serve on {host}:{port}: {exc.strerror}; set "
                                f"[services.panel.main] port to a free port in the deployment file") from None
