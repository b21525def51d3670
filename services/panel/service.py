"""panel node: the viser dashboard at http://<host>:<port> (default http://127.0.0.1:8080).

Subscriptions only keep the latest message per key (event loop); a render loop draws at ``fps``
from that state, never per message, and only while a browser is connected. GUI callbacks run on
viser's worker threads and only issue Zenoh queries, so they never touch the loop's state.
"""

from __future__ import annotations

import asyncio
import json
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import cv2
import numpy as np
import trimesh
import viser

from services.panel import executions, page, view
from services.panel.alerts import Alert, Alerts
from services.panel.execute import Execute
from services.panel.jobs import Trainer
from services.panel.learn import Learn
from services.panel.neural import NeuralSim
from services.panel.teaching import Teaching
from shared import msgs
from shared.config import ConfigError, load_deployment
from shared.geometry import wxyz
from shared.keys import CAMERAS, GLOVES
from shared.kinematics import RobotModel, URDFError, load_robot
from shared.robots.registry import DEFAULT_ROBOT, REGISTRY
from shared.runtime import EndpointError, Node

RECORDER = "xm/recorder/main/@cmd"
FRAME_SIZE = 0.8  # the aluminium frame around the table, metres (services/world/model.py)
FRAME_HEIGHT = 0.8
TACTILE_MESH_STALE_S = 2.0  # a hand's tactile mesh is hidden when recon has not sent it for this long
TRAJECTORY_STALE_S = 1.0  # trajopt sends 10 a second: the drawn trajectory is hidden after this long without one


class PanelService:
    # Set by __main__ from --deployment: an empty ``recordings`` is the recorder's directory there.
    deployment: ClassVar[str] = ""

    @dataclass
    class Params:
        port: int = 8080
        host: str = "127.0.0.1"
        fps: float = 15.0  # scene redraw rate while a browser is connected
        tactile_hz: float = 5.0  # heatmap and camera thumbnail refresh (images are the heavy part)
        camera: str = "cam0"  # initial thumbnail camera
        health_period_s: float = 2.0
        robot: str = DEFAULT_ROBOT  # a described robot (shared/robots/registry.py)
        recordings: str = ""  # the demonstration library; empty: [services.recorder.main] directory
        models: str = "runs/models"  # where training jobs started from the page write their models
        # torch threads of a training job: one, as the cell takes about a core of a 2-core host beside it and a
        # second thread stalls each step at torch's barrier whenever another process holds its core (docs/panel.md)
        train_threads: int = 1
        train_share: int = 10  # a job's session this many nice values below the services': about a core (docs/panel.md)
        train_args: str = ""  # more `xm train` options for those jobs, e.g. "--set hidden=64,64"
        # A fresh install's first network: trained as the page's job when this checkpoint (the policy
        # service's) is missing, while the policy service runs the naive fallback ("": never).
        first_network: str = ""
        first_preset: str = "no_tactile"
        # its optimizer steps (its own cosine schedule), fewer than the preset's 8000 so that it is served
        # within 15 minutes beside the running cell (docs/panel.md, first run)
        first_steps: int = 5000

    def __init__(self, node: Node, params: Params) -> None:
        if params.fps <= 0 or params.tactile_hz <= 0:
            raise EndpointError(f"panel: fps ({params.fps}) and tactile_hz ({params.tactile_hz}) must be > 0")
        self.node = node
        self.p = params
        check_port(params.host, params.port)
        self.robot: RobotModel | None = None
        self.robot_problem = ""
        try:
            self.robot = load_robot(params.robot)
        except (FileNotFoundError, URDFError) as exc:  # draw joint markers instead, and say why
            self.robot_problem = str(exc)
            node.log.warning("no robot model, drawing joint markers: %s", exc)
        self.latest: dict[str, Any] = {}
        self.world_session: Any = None  # the newest Session message drawn
        self.camera_choice = params.camera if params.camera in CAMERAS else CAMERAS[0]
        self.frames_drawn = 0
        self._last_images = 0.0
        self._frustum_p: dict[str, tuple] = {}
        self._logged: set[str] = set()
        self._mesh_seen: dict[str, float] = {}  # hand -> when its tactile mesh was last drawn
        self._mesh_view: tuple[np.ndarray, np.ndarray] | None = None  # camera facing the most pressed hand
        # the robot's points that execute the plan (shared/robots): the trajectory is drawn as their paths
        desc = REGISTRY.get(params.robot)
        self.trajectory_frames = list(dict.fromkeys(desc.point_map.values())) if desc and self.robot else []
        self._trajectory_seen = -np.inf  # when the last trajectory was drawn (monotonic)
        self.trajectories_drawn = 0
        self.alerts = Alerts(missing_after_s=3 * params.health_period_s)
        self.server = viser.ViserServer(host=params.host, port=params.port, verbose=False)
        if self.server.get_port() != params.port:  # viser silently moves to the next free port
            self.server.stop()
            raise EndpointError(port_message(params.host, params.port, "taken while starting"))
        page.hold_clicks(self.server)  # a press must not overtake the typed values (services/panel/page.py)
        self._build_scene()
        self._build_gui()
        recordings = recordings_directory(params.recordings, self.deployment)
        self.teaching = Teaching(self.server, recordings, self._query_recorder, lambda: self.world_session,
                                 node.stats.count)
        self.execute = Execute(self.server, params.robot, self._query, node.stats.count,
                               recordings / executions.LOG_NAME, self.teaching.context,
                               lambda e: self.teaching.executed(e.success))
        self.learn = Learn(self.server, recordings, Trainer(params.models, params.train_args, params.train_threads,
                                                                 params.train_share),
                           lambda: self.teaching.entries, lambda: self.execute.serving, node.stats.count)
        self.learn.on_models.append(self.execute.set_models)
        self.neural = NeuralSim(self.server, self._query, self._reviewed_scene, node.stats.count)
        self.learn.on_models.append(self.neural.set_models)
        if params.first_network:
            self.learn.start_first(Path(params.first_network), params.first_preset, params.first_steps)
        # state: robot/<model>/state (ports.py)
        for port in ("state", "scene", "plan", "trajectory", "session", "tactile_mesh"):
            node.input(port, self._keeper(port))
        for port in ("tactile", "info", "image"):  # one message per hand / camera
            node.input(port, self._keeper(port, by_source=True))
        node.health_extra = self._health_extra

    @property
    def url(self) -> str:
        return f"http://{self.p.host}:{self.p.port}"

    def _health_extra(self) -> dict:
        return {"url": self.url, "clients": len(self.server.get_clients()), "frames_drawn": self.frames_drawn,
                "trajectory": {"frames": self.trajectory_frames, "drawn": self.trajectories_drawn,
                               "shown": bool(self.trajectory.visible)},
                "robot_model": self.robot is not None, "frustums": sorted(self.frustums),
                "tactile_meshes": sorted(h for h, m in self.tactile_meshes.items() if m.visible),
                "alerts": [{"level": a.level, "title": a.title, "body": a.body} for a in self.alerts.recent],
                **self.teaching.health(), **self.learn.health(), **self.execute.health(), **self.neural.health()}

    def _keeper(self, port: str, by_source: bool = False) -> Callable[[Any, str], None]:
        """Handler keeping the newest message of ``port``, per hand or camera (the key's third chunk)
        when ``by_source``: ``latest["tactile/left"]``, ``latest["info/cam0"]``."""
        def keep(msg: Any, key: str) -> None:
            self.latest[f"{port}/{key.split('/')[2]}" if by_source else port] = msg
        return keep

    # --- layout -------------------------------------------------------------------------
    def _build_scene(self) -> None:
        sc = self.server.scene
        sc.set_up_direction("+z")
        self.server.initial_camera.position = (1.1, -0.9, 0.9)
        self.server.initial_camera.look_at = (0.0, 0.0, 0.2)
        self.server.initial_camera.up = (0.0, 0.0, 1.0)
        half = FRAME_SIZE / 2
        sc.add_grid("/table", width=FRAME_SIZE, height=FRAME_SIZE, cell_size=0.05, section_size=0.4, plane="xy")
        sc.add_frame("/world", axes_length=0.08, axes_radius=0.003)
        for x in (-half, half):
            for y in (-half, half):
                sc.add_box(f"/frame/post_{x:+.1f}_{y:+.1f}", color=(80, 80, 80), dimensions=(0.02, 0.02, FRAME_HEIGHT),
                           position=(x, y, FRAME_HEIGHT / 2))
        self.links: dict[str, Any] = {}
        if self.robot is not None:
            for box in view.link_boxes(self.robot, np.zeros(len(self.robot.joint_names))):
                self.links[box.name] = sc.add_box(f"/robot/{box.name}", color=(180, 185, 195),
                                                  dimensions=tuple(box.dimensions), position=box.pose[:3, 3],
                                                  wxyz=wxyz(box.pose[:3, :3]))
            self.markers = None
        else:
            self.markers = sc.add_line_segments("/robot/joint_markers", np.zeros((1, 2, 3)), (200, 120, 40),
                                                thickness=0.012, visible=False)
        self.hand_lines = {h: sc.add_line_segments(f"/hands/{h}", np.zeros((20, 2, 3)), view.HAND_COLORS[h],
                                                   thickness=0.004, visible=False) for h in GLOVES}
        self.hand_points = {h: sc.add_point_cloud(f"/hands/{h}_points", np.zeros((21, 3)), view.HAND_COLORS[h],
                                                  point_size=0.008, point_shape="circle", visible=False)
                            for h in GLOVES}
        self.objects = sc.add_point_cloud("/objects", np.zeros((1, 3)), (0, 0, 0), point_size=0.012,
                                          point_shape="circle", visible=False)
        self.plan = sc.add_line_segments("/plan", np.zeros((1, 2, 3)), view.PLAN_COLOR, thickness=0.003,
                                         visible=False)
        # the optimizer's trajectory: each executing point's path over the knots, its end a dot
        self.trajectory = sc.add_line_segments("/trajectory", np.zeros((1, 2, 3)), view.TRAJECTORY_COLOR,
                                               thickness=0.006, visible=False)
        self.trajectory_ends = sc.add_point_cloud("/trajectory_ends", np.zeros((1, 3)), view.TRAJECTORY_COLOR,
                                                  point_size=0.014, point_shape="diamond", visible=False)
        self.frustums: dict[str, Any] = {}
        self.tactile_meshes: dict[str, Any] = {}  # hand -> GLB handle (its data replaced on every draw)

    def _build_gui(self) -> None:
        gui = self.server.gui
        self.session_md = gui.add_markdown("**session**: waiting for `xm/world/sim/session`")
        if self.robot is None:
            gui.add_markdown(f"**robot model unavailable** ({self.robot_problem}): bars show |q| per joint")
        with gui.add_folder("Tactile"):
            blank = view.tactile_image(np.zeros(256), scale=8)
            self.tactile_images = {h: gui.add_image(blank, label=f"{h} glove", format="png") for h in GLOVES}
            look = gui.add_button("Look at the gloved hand")
            look.on_click(self._look_at_glove)
        with gui.add_folder("Camera"):
            dropdown = gui.add_dropdown("camera", list(CAMERAS), initial_value=self.camera_choice)
            dropdown.on_update(lambda _e: setattr(self, "camera_choice", dropdown.value))
            self.camera_image = gui.add_image(np.zeros((120, 160, 3), np.uint8), label="view", format="jpeg")
        with gui.add_folder("Services"):
            self.status_md = gui.add_markdown("querying `xm/**/@health`...")
        with gui.add_folder("Alerts"):  # also shown as toasts when they happen
            self.alerts_md = gui.add_markdown("no alerts")

    def _look_at_glove(self, event: Any) -> None:
        """viser worker thread: moves the clicking browser's camera to the palm side of the hand
        whose tactile mesh carries the most pressure (it only reads the tuple the loop replaces)."""
        pose = self._mesh_view
        if pose is not None and event.client is not None:
            event.client.camera.position, event.client.camera.look_at = pose

    def _query_recorder(self, verb: str, request: dict) -> list[dict]:
        return self._query(f"{RECORDER}/{verb}", request)

    def _query(self, key: str, request: dict, timeout: float = 5.0) -> list[dict]:
        """viser worker thread (or a folder's own): a blocking query is fine here."""
        return [json.loads(r.ok.payload.to_bytes())
                for r in self.node.session.get(key, payload=json.dumps(request), timeout=timeout) if r.ok is not None]

    def _reviewed_scene(self) -> Any:
        """The Scene message of the reviewed demonstration at the scrubber, or None."""
        review = self.teaching.review
        return None if review is None else review.timeline.frame(review.head.position).get("scene")

    # --- loops --------------------------------------------------------------------------
    async def run(self) -> None:
        self.node.spawn(self._status_loop(), name="status")
        period = 1.0 / self.p.fps
        while True:
            t0 = time.monotonic()
            if self.server.get_clients():  # nobody watching: only keep the latest state
                try:
                    with self.server.atomic():
                        self._draw(t0)
                    self.frames_drawn += 1
                except Exception as exc:  # a bad message must not stop the dashboard
                    self.node.stats.count("draw_error")
                    if repr(exc) not in self._logged:  # once per distinct error, not per frame
                        self._logged.add(repr(exc))
                        self.node.log.warning("draw failed: %r", exc, exc_info=exc)
            await asyncio.sleep(max(0.0, period - (time.monotonic() - t0)))

    def _pop(self, key: str) -> Any:
        return self.latest.pop(key, None)

    def _draw(self, now: float) -> None:
        """The live state, or while a demonstration is reviewed its replayed messages at the scrubber."""
        self.teaching.tick(now)
        self.neural.tick(now)
        if self.teaching.reviewing:
            replayed = self.teaching.review_frame(now)

            def take(key: str) -> Any:
                return replayed.pop(key, None)
        else:
            take = self._pop
        self._draw_robot(take("state"))
        self._draw_scene(take("scene"))
        self._draw_plan(take("plan"))
        self._draw_trajectory(take("trajectory"), now)
        for cam in CAMERAS:
            info = take(f"info/{cam}")
            if info is not None:
                self._draw_frustum(cam, info)
        session = take("session")
        if session is not None:
            if not self.teaching.reviewing:
                self.world_session = session
                self.teaching.offer_world_session(session)
            self.session_md.content = view.session_text(session, msgs.stamp_seconds(session.header.stamp))
        if now - self._last_images >= 1.0 / self.p.tactile_hz:
            self._last_images = now
            self._draw_images(take)
            self._draw_tactile_mesh(take("tactile_mesh"), now)

    def _draw_robot(self, state: Any) -> None:
        if state is None:
            return
        if self.robot is None:
            self.markers.points = view.joint_markers(state.position)
            self.markers.visible = True
            return
        q = view.joint_vector(self.robot.joint_names, state.name, state.position)
        for box in view.link_boxes(self.robot, q):
            handle = self.links[box.name]
            handle.position = box.pose[:3, 3]
            handle.wxyz = wxyz(box.pose[:3, :3])

    def _draw_scene(self, scene: Any) -> None:
        if scene is None:
            return
        hands, masks = view.hand_arrays(scene.hand_keypoints, scene.hand_mask, len(scene.hand_names))
        for i, name in enumerate(scene.hand_names):
            if name not in self.hand_lines:
                continue
            seg, bright = view.hand_segments(hands[i], masks[i])
            lines, points = self.hand_lines[name], self.hand_points[name]
            lines.points = seg
            lines.colors = view.segment_colors(view.HAND_COLORS[name], bright)
            points.points = hands[i].astype(np.float32)
            points.colors = view.point_colors(view.HAND_COLORS[name], masks[i])
            lines.visible = points.visible = bool(masks[i].any())
        pts = np.asarray(scene.object_keypoints, np.float32).reshape(-1, 3)
        if len(pts) and len(pts) == len(scene.object_names):
            self.objects.points = pts
            self.objects.colors = view.object_colors(list(scene.object_names), scene.object_mask)
        self.objects.visible = bool(len(pts))

    def _draw_plan(self, plan: Any) -> None:
        if plan is None:
            return
        seg = view.plan_segments(plan.positions, plan.mask, int(plan.steps), len(plan.point_names))
        if len(seg):
            self.plan.points = seg
            self.plan.colors = np.broadcast_to(np.array(view.PLAN_COLOR, np.uint8), seg.shape).copy()
        self.plan.visible = bool(len(seg))

    def _draw_trajectory(self, msg: Any, now: float) -> None:
        """Where the robot's executing points go over the optimizer's knots; hidden live when trajopt
        has not sent a trajectory for TRAJECTORY_STALE_S (a review shows the recorded one as it stands)."""
        if msg is not None and self.trajectory_frames:
            try:
                paths = view.trajectory_paths(self.robot, self.trajectory_frames, list(msg.joint_names),
                                              [p.positions for p in msg.points])
            except view.ViewError as exc:  # counted and skipped: the rest of the frame still draws
                self.node.stats.count("bad_trajectory")
                self.node.log.debug("trajectory: %s", exc)
                return
            seg = view.path_segments(paths)
            if len(seg):
                self.trajectory.points = seg
                self.trajectory.colors = np.broadcast_to(np.array(view.TRAJECTORY_COLOR, np.uint8), seg.shape).copy()
            self.trajectory_ends.points = paths[:, -1].astype(np.float32)
            self.trajectory_ends.colors = np.broadcast_to(np.array(view.TRAJECTORY_COLOR, np.uint8),
                                                          (len(paths), 3)).copy()
            self.trajectory.visible = bool(len(seg))
            self.trajectory_ends.visible = True
            self._trajectory_seen = now
            self.trajectories_drawn += 1
        elif (self.trajectory_ends.visible and not self.teaching.reviewing
              and now - self._trajectory_seen > TRAJECTORY_STALE_S):
            self.trajectory.visible = self.trajectory_ends.visible = False

    def _draw_frustum(self, cam: str, info: Any) -> None:
        p = tuple(np.asarray(info.p, float).round(6))
        if self._frustum_p.get(cam) == p:
            return
        try:
            f = view.camera_frustum(info.p, int(info.width), int(info.height))
        except view.ViewError as exc:
            self.node.stats.count("bad_camera_info", cam)
            self.node.log.warning("camera %s: %s", cam, exc)
            self._frustum_p[cam] = p  # complain once per distinct P
            return
        self._frustum_p[cam] = p
        if cam in self.frustums:
            self.frustums[cam].remove()
        self.frustums[cam] = self.server.scene.add_camera_frustum(
            f"/cameras/{cam}", fov=f.fov, aspect=f.aspect, scale=0.06, wxyz=f.wxyz, position=f.position,
            color=(40, 40, 40), thickness=0.002)
        self.server.scene.add_label(f"/cameras/{cam}/label", cam)

    def _draw_images(self, take: Callable[[str], Any]) -> None:
        for hand in GLOVES:
            msg = take(f"tactile/{hand}")
            if msg is not None:
                self.tactile_images[hand].image = view.tactile_image(msg.pressure, msg.mask, int(msg.rows),
                                                                     int(msg.cols), scale=8)
        image = take(f"image/{self.camera_choice}")
        if image is not None:
            bgr = cv2.imdecode(np.frombuffer(bytes(image.data), np.uint8), cv2.IMREAD_COLOR)
            if bgr is None:
                self.node.stats.count("bad_jpeg", self.camera_choice)
            else:
                self.camera_image.image = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)

    def _draw_tactile_mesh(self, msg: Any, now: float) -> None:
        """Each gloved hand's surface, coloured by pressure; hidden once recon stops sending it."""
        if msg is not None:
            sensed = np.asarray(msg.sensed, np.uint8)
            hands = view.tactile_mesh_arrays(msg.hand_names, msg.vertex_count, msg.vertices, msg.faces, msg.pressure,
                                             sensed)
            if hands:
                _, verts, _, _ = max(hands, key=lambda h: float(np.sum(h[3])))
                self._mesh_view = view.palm_side_view(verts, sensed)
            for name, verts, faces, pressure in hands:
                colors = view.tactile_mesh_colors(pressure, sensed, view.HAND_COLORS.get(name, (200, 200, 200)))
                glb = trimesh.Trimesh(verts, faces, vertex_colors=colors, process=False).export(
                    file_type="glb", include_normals=True)  # with normals: shaded smooth, not flat
                if name in self.tactile_meshes:  # in place: the browser keeps the node (and its shadow)
                    self.tactile_meshes[name].glb_data = glb
                else:
                    self.tactile_meshes[name] = self.server.scene.add_glb(f"/hands/{name}_tactile", glb)
                self._mesh_seen[name] = now
        for name, handle in self.tactile_meshes.items():
            fresh = now - self._mesh_seen.get(name, -np.inf) < TACTILE_MESH_STALE_S
            if handle.visible != fresh:
                handle.visible = fresh

    async def _status_loop(self) -> None:
        """Health rounds also while nobody watches: the alerts a browser opened later lists stay true."""
        while True:
            reports = await in_daemon_thread(self._query_health)
            fresh = self.alerts.update(reports, time.monotonic())
            if fresh:
                self.alerts_md.content = view.alerts_text(list(self.alerts.recent))
            if self.server.get_clients():
                for alert in fresh:
                    self._toast(alert)
                self.status_md.content = view.health_table(reports)
                self.execute.update(reports)
            await asyncio.sleep(self.p.health_period_s)

    def _toast(self, alert: Alert) -> None:
        for client in list(self.server.get_clients().values()):
            try:
                client.add_notification(alert.title, alert.body, color=alert.color,
                                        auto_close_seconds=30.0 if alert.level == "error" else 10.0)
            except Exception as exc:  # a browser that left meanwhile
                self.node.stats.count("toast_error")
                self.node.log.debug("toast: %r", exc)

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
        self.neural.close()
        self.learn.close()
        self.teaching.close()
        self.server.stop()


async def in_daemon_thread(fn: Callable[[], Any]) -> Any:
    """``fn()`` on a daemon thread of its own: unlike ``asyncio.to_thread``, the process's shutdown
    does not wait for it (a Zenoh query in flight when the session closes may never return)."""
    loop = asyncio.get_running_loop()
    future = loop.create_future()

    def settle(value: Any, exc: BaseException | None) -> None:
        if not future.done():
            future.set_result(value) if exc is None else future.set_exception(exc)

    def run() -> None:
        try:
            value, exc = fn(), None
        except Exception as error:
            value, exc = None, error
        try:
            loop.call_soon_threadsafe(settle, value, exc)
        except RuntimeError:  # the loop has closed: nobody waits for the answer
            pass

    threading.Thread(target=run, name="panel-health", daemon=True).start()
    return await future


def recordings_directory(param: str, deployment: str) -> Path:
    """The library's directory: the parameter, else the deployment's recorder's, else ``recordings``."""
    if param:
        return Path(param)
    if deployment:
        try:
            directory = load_deployment(deployment).services.get("recorder", {}).get("main", {}).get("directory")
        except (ConfigError, OSError):
            directory = None
        if isinstance(directory, str) and directory:
            return Path(directory)
    return Path("recordings")


def port_message(host: str, port: int, why: str) -> str:
    return (f"panel: cannot serve the dashboard on {host}:{port}: {why}. Another panel is running? "
            f"Stop it, or set `port = <free port>` under [services.panel.<instance>] in the deployment file")


def check_port(host: str, port: int) -> None:
    """Fail with a readable EndpointError (exit code 2) when the dashboard port is taken."""
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind((host, port))
        except OSError as exc:
            raise EndpointError(port_message(host, port, exc.strerror or str(exc))) from None
