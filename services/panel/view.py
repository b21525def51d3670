"""Messages -> drawable arrays for the dashboard (pure: no viser, no Zenoh).

Everything here takes numpy arrays or message-like objects (attribute access only) and returns
arrays, strings or small tuples, so the service only moves them into viser handles.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from matplotlib import colormaps

from shared.geometry import pose_from_projection, wxyz
from shared.kinematics import RobotModel

KEYPOINTS = 21
# MANO/OpenPose bones: thumb chain from the wrist, then wrist -> each finger base and along the finger.
BONES: list[tuple[int, int]] = [(0, 1), (1, 2), (2, 3), (3, 4)] + [
    pair for b in (5, 9, 13, 17) for pair in ((0, b), (b, b + 1), (b + 1, b + 2), (b + 2, b + 3))]
HAND_COLORS = {"left": (230, 120, 90), "right": (90, 120, 230)}
DIM = 0.35  # brightness of what a mask marks unobserved
PLAN_COLOR = (60, 190, 90)
TRAJECTORY_COLOR = (240, 150, 30)  # the optimizer's joint trajectory, drawn as its points' paths
TACTILE_SHAPE = (16, 16)


class ViewError(ValueError):
    """A message whose arrays do not have the sizes its own fields promise."""


# --- hands and objects ------------------------------------------------------------------------

def hand_arrays(hand_keypoints: Sequence[float], hand_mask: Sequence[int] | None,
                hands: int) -> tuple[np.ndarray, np.ndarray]:
    """Flat Scene fields -> (H,21,3) keypoints and (H,21) bool mask (all observed when the mask is empty)."""
    pts = np.asarray(hand_keypoints, float)
    if pts.size != hands * KEYPOINTS * 3:
        raise ViewError(f"hand_keypoints has {pts.size} values, expected {hands}*21*3 = {hands * KEYPOINTS * 3}")
    mask = np.asarray(hand_mask if hand_mask is not None else [], np.uint8)
    if mask.size == 0:
        mask = np.ones(hands * KEYPOINTS, np.uint8)
    if mask.size != hands * KEYPOINTS:
        raise ViewError(f"hand_mask has {mask.size} values, expected {hands * KEYPOINTS}")
    return pts.reshape(hands, KEYPOINTS, 3), mask.reshape(hands, KEYPOINTS).astype(bool)


def hand_segments(hand: np.ndarray, mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(20,2,3) bone segments of one hand and per-segment brightness: 1 if both ends observed, else DIM."""
    hand = np.asarray(hand, float)
    if hand.shape != (KEYPOINTS, 3):
        raise ViewError(f"hand has shape {hand.shape}, expected (21, 3)")
    idx = np.array(BONES)
    seen = np.ones(len(idx)) if mask is None else np.where(np.asarray(mask, bool)[idx].all(axis=1), 1.0, DIM)
    return hand[idx], seen


def segment_colors(base: tuple[int, int, int], brightness: np.ndarray) -> np.ndarray:
    """(N,2,3) uint8 colours: the base colour scaled per segment."""
    c = np.asarray(base, float)[None, None, :] * np.asarray(brightness, float)[:, None, None]
    return np.repeat(c, 2, axis=1).round().astype(np.uint8)


def point_colors(base: tuple[int, int, int], mask: np.ndarray) -> np.ndarray:
    """(N,3) uint8: base colour where observed, dimmed elsewhere."""
    scale = np.where(np.asarray(mask, bool), 1.0, DIM)
    return (np.asarray(base, float)[None, :] * scale[:, None]).round().astype(np.uint8)


def object_colors(names: Sequence[str], mask: Sequence[int] | None = None) -> np.ndarray:
    """(N,3) uint8, one tab10 colour per object (the part of "<object>/<point>" before '/'), dimmed if unseen."""
    objects = sorted({n.split("/")[0] for n in names})
    palette = (np.asarray(colormaps["tab10"].colors)[:, :3] * 255).round()
    rgb = np.array([palette[objects.index(n.split("/")[0]) % len(palette)] for n in names]).reshape(-1, 3)
    if mask is not None and len(mask) == len(names):
        rgb = rgb * np.where(np.asarray(mask, bool), 1.0, DIM)[:, None]
    return rgb.round().astype(np.uint8)


# --- plan ---------------------------------------------------------------------------------

def plan_segments(positions: Sequence[float], mask: Sequence[int] | None, steps: int,
                  points: int) -> np.ndarray:
    """Plan fields -> (S,2,3) segments joining each keypoint's consecutive steps where both are valid."""
    pos = np.asarray(positions, float)
    if steps < 2 or points == 0:
        return np.zeros((0, 2, 3))
    if pos.size != steps * points * 3:
        raise ViewError(f"plan positions has {pos.size} values, expected {steps}*{points}*3")
    pos = pos.reshape(steps, points, 3)
    m = np.asarray(mask if mask is not None else [], bool)
    m = np.ones((steps, points), bool) if m.size == 0 else m.reshape(steps, points)
    ok = m[:-1] & m[1:]  # (steps-1, points)
    return np.stack([pos[:-1][ok], pos[1:][ok]], axis=1)


# --- tactile ------------------------------------------------------------------------------

def tactile_image(pressure: Sequence[float], mask: Sequence[int] | None = None, rows: int = 16, cols: int = 16,
                  vmax: float = 30.0, scale: int = 12) -> np.ndarray:
    """rows x cols pressure (kPa) -> (rows*scale, cols*scale, 3) uint8 inferno heatmap, absent cells grey."""
    p = np.asarray(pressure, float)
    if p.size != rows * cols:
        raise ViewError(f"tactile pressure has {p.size} values, expected {rows}x{cols}")
    level = np.clip(np.nan_to_num(p.reshape(rows, cols)) / vmax, 0.0, 1.0)
    rgb = (colormaps["inferno"](level)[..., :3] * 255).round().astype(np.uint8)
    if mask is not None and len(mask) == rows * cols:
        rgb[np.asarray(mask).reshape(rows, cols) == 0] = (40, 40, 40)
    return np.kron(rgb, np.ones((scale, scale, 1), np.uint8))


def tactile_mesh_arrays(hand_names: Sequence[str], vertex_count: int, vertices: Sequence[float],
                        faces: Sequence[int], pressure: Sequence[float], sensed: Sequence[int] | None = None
                        ) -> list[tuple[str, np.ndarray, np.ndarray, np.ndarray]]:
    """TactileMesh fields -> per hand (name, vertices (N,3) float32, faces (F,3) int, pressure (N,));
    ``sensed``, when given, must have one flag per vertex."""
    names, n = list(hand_names), int(vertex_count)
    h = len(names)
    v, p, f = np.asarray(vertices, np.float32), np.asarray(pressure, np.float32), np.asarray(faces, np.int64)
    if v.size != h * n * 3 or p.size != h * n:
        raise ViewError(f"tactile mesh has {v.size} vertex values and {p.size} pressures, "
                        f"expected {h}*{n}*3 and {h}*{n}")
    if sensed is not None and len(sensed) != n:
        raise ViewError(f"tactile mesh has {len(sensed)} sensed flags for {n} vertices")
    if h == 0:
        return []
    if f.size % (3 * h):
        raise ViewError(f"tactile mesh has {f.size} face indices: not {h} hands of triangles")
    f = f.reshape(h, -1, 3)
    if f.size and (f.min() < 0 or f.max() >= n):
        raise ViewError(f"tactile mesh face index outside 0..{n - 1}")
    v, p = v.reshape(h, n, 3), p.reshape(h, n)
    return [(names[i], v[i], f[i], p[i]) for i in range(h)]


def tactile_mesh_colors(pressure: Sequence[float], sensed: Sequence[int], base: tuple[int, int, int],
                        vmax: float = 30.0) -> np.ndarray:
    """(N,3) uint8 vertex colours: sensed vertices on the heatmaps' inferno scale (0-vmax kPa),
    the rest in the hand's colour."""
    p = np.asarray(pressure, float)
    s = np.asarray(sensed, bool)
    if s.shape != p.shape:
        raise ViewError(f"tactile mesh has {s.size} sensed flags for {p.size} vertices")
    level = np.clip(np.nan_to_num(p) / vmax, 0.0, 1.0)
    rgb = colormaps["inferno"](level)[:, :3] * 255
    return np.where(s[:, None], rgb, np.asarray(base, float)[None, :]).round().astype(np.uint8)


def palm_side_view(vertices: np.ndarray, sensed: Sequence[int], distance: float = 0.3,
                   elevation_deg: tuple[float, float] = (-45.0, 60.0)) -> tuple[np.ndarray, np.ndarray]:
    """(camera position, look-at point) facing a hand's sensors: the camera stands off the mesh's
    centre on the side the sensors face (they sit on the palm side), its elevation above the
    table's plane held within ``elevation_deg`` (a palm turned down is seen obliquely from below)."""
    v = np.asarray(vertices, float)
    centre = v.mean(axis=0)
    s = np.asarray(sensed, bool)
    toward = v[s].mean(axis=0) - centre if s.any() else np.zeros(3)
    toward /= max(np.linalg.norm(toward), 1e-12)
    horizontal = toward[:2] if np.linalg.norm(toward[:2]) > 1e-6 else np.array([1.0, -1.0])  # the default side
    e = np.clip(np.arcsin(np.clip(toward[2], -1.0, 1.0)), *np.radians(elevation_deg))
    direction = np.append(np.cos(e) * horizontal / np.linalg.norm(horizontal), np.sin(e))
    return centre + distance * direction, centre


# --- robot --------------------------------------------------------------------------------

def joint_vector(model_names: Sequence[str], names: Sequence[str], positions: Sequence[float]) -> np.ndarray:
    """JointState (names, positions) in the model's joint order; joints the message lacks stay at 0."""
    given = dict(zip(names, np.asarray(positions, float), strict=False))
    return np.array([given.get(n, 0.0) for n in model_names])


@dataclass(frozen=True)
class LinkBox:
    name: str
    dimensions: np.ndarray  # full extents (3,)
    pose: np.ndarray  # world 4x4 of the box centre


def _shape_box(kind: str, size: np.ndarray, vertices: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(dimensions, centre in the shape frame): a box approximating the shape."""
    if kind == "box":
        return np.asarray(size, float), np.zeros(3)
    if kind == "cylinder":
        return np.array([2 * size[0], 2 * size[0], size[1]]), np.zeros(3)
    if kind == "sphere":
        return np.full(3, 2 * size[0]), np.zeros(3)
    if vertices is not None and len(vertices):  # mesh: its bounding box
        lo, hi = vertices.min(axis=0), vertices.max(axis=0)
        return np.maximum(hi - lo, 1e-3), (hi + lo) / 2
    return np.full(3, 0.02), np.zeros(3)


def link_boxes(model: RobotModel, q: np.ndarray) -> list[LinkBox]:
    """One box per collision shape at its forward-kinematics pose."""
    poses = model.fk(np.asarray(q, float))
    out = []
    for i, s in enumerate(model.shapes):
        dims, centre = _shape_box(s.kind, s.size, s.vertices)
        offset = np.eye(4)
        offset[:3, 3] = centre
        out.append(LinkBox(f"{s.link}_{i}", dims, poses[s.link] @ s.origin @ offset))
    return out


def trajectory_paths(model: RobotModel, frames: Sequence[str], joint_names: Sequence[str],
                     knots: Sequence[Sequence[float]]) -> np.ndarray:
    """(F, K, 3): where each of ``frames`` (the robot's points that execute the plan) goes over the
    optimizer's K knots (JointTrajectory points; joints a knot lacks stay at 0). ViewError for an
    empty trajectory or an unknown frame."""
    unknown = [f for f in frames if f not in model.frames()]
    if unknown or not frames:
        raise ViewError(f"trajectory: no such robot frames {unknown}" if unknown else "trajectory: no frames to draw")
    if not len(knots):
        raise ViewError("trajectory without points")
    out = np.zeros((len(frames), len(knots), 3))
    for k, positions in enumerate(knots):
        if len(positions) != len(joint_names):
            raise ViewError(f"trajectory point {k} has {len(positions)} positions for {len(joint_names)} joints")
        poses = model.fk(joint_vector(model.joint_names, joint_names, positions))
        for i, f in enumerate(frames):
            out[i, k] = poses[f][:3, 3]
    return out


def path_segments(paths: np.ndarray) -> np.ndarray:
    """(F, K, 3) paths -> (F * (K - 1), 2, 3) line segments joining consecutive knots."""
    paths = np.asarray(paths, np.float32)
    return np.stack([paths[:, :-1], paths[:, 1:]], axis=2).reshape(-1, 2, 3)


def joint_markers(positions: Sequence[float], spacing: float = 0.05, origin: Sequence[float] = (-0.35, -0.45, 0.0),
                  gain: float = 0.5) -> np.ndarray:
    """Fallback without a robot model: (N,2,3) vertical bars along the table edge, height = |q|*gain."""
    q = np.abs(np.asarray(positions, float))
    x = origin[0] + spacing * np.arange(len(q))
    base = np.stack([x, np.full_like(x, origin[1]), np.full_like(x, origin[2])], axis=1)
    top = base + np.stack([np.zeros_like(q), np.zeros_like(q), np.maximum(q * gain, 0.005)], axis=1)
    return np.stack([base, top], axis=1)


# --- cameras ------------------------------------------------------------------------------

@dataclass(frozen=True)
class Frustum:
    fov: float  # vertical, rad
    aspect: float  # width / height
    wxyz: np.ndarray
    position: np.ndarray


def camera_frustum(p: Sequence[float], width: int, height: int) -> Frustum:
    """CameraInfo's P = K[R|t] (world -> pixels) -> the camera's world pose and field of view (OpenCV axes)."""
    P = np.asarray(p, float)
    if P.size != 12 or not np.isfinite(P).all() or abs(np.linalg.det(P.reshape(3, 4)[:, :3])) < 1e-12:
        raise ViewError("CameraInfo.p is not a full-rank K[R|t]; camhub must fill it with the camera pose")
    if width <= 0 or height <= 0:
        raise ViewError(f"CameraInfo size {width}x{height} is not positive")
    K, world_T_cam = pose_from_projection(P)
    fov = 2.0 * np.arctan(height / (2.0 * abs(K[1, 1])))
    return Frustum(float(fov), width / height, wxyz(world_T_cam[:3, :3]), world_T_cam[:3, 3].copy())


# --- text ---------------------------------------------------------------------------------

def session_text(session: Any, t: float) -> str:
    return (f"**{session.task or '?'}** demo {session.demo}, phase **{session.phase or '?'}**, "
            f"glove on the {session.tactile_hand or '?'} hand, t = {t:.1f} s")


def _rates(hz: dict) -> str:
    """Rates by topic (the key's last chunk); several keys of one topic read "image 7x5"."""
    groups: dict[str, list[float]] = {}
    for key, rate in hz.items():
        groups.setdefault(key.rsplit("/", 1)[-1], []).append(float(rate))
    parts = []
    for topic, rates in sorted(groups.items()):
        mean = sum(rates) / len(rates)
        parts.append(f"{topic} {mean:.3g}" if len(rates) == 1 else f"{topic} {len(rates)}x{mean:.3g}")
    return ", ".join(parts) or "-"


def health_table(reports: Sequence[dict]) -> str:
    """@health replies -> a markdown table, one row per service instance, sorted."""
    if not reports:
        return "no service answered `xm/**/@health`"
    rows = ["| service | status | pid | up s | out Hz | in keys | errors |", "|---|---|---|---|---|---|---|"]
    for r in sorted(reports, key=lambda r: (str(r.get("service", "")), str(r.get("instance", "")))):
        errors = r.get("errors") or {}
        err = ", ".join(f"{k} {v}" for k, v in sorted(errors.items())) or "-"
        status = str(r.get("status", "?"))
        if r.get("message"):
            status += ": " + str(r["message"]).replace("|", "/")
        up = r.get("uptime_s")
        up_text = f"{up:.0f}" if isinstance(up, (int, float)) else "-"
        rows.append(f"| {r.get('service', '?')}/{r.get('instance', '?')} | {status} | {r.get('pid', '-')} | "
                    f"{up_text} | {_rates(r.get('published_hz') or {})} | "
                    f"{len(r.get('received_hz') or {})} | {err} |")
    return "\n".join(rows)


def recorder_text(verb: str, replies: Sequence[dict]) -> str:
    """The recorder's JSON reply -> one line for the GUI."""
    if not replies:
        return "**error**: no recorder answered `xm/recorder/main/@cmd/" + verb + "` (is the recorder running?)"
    reply = replies[0]
    if not reply.get("ok"):
        return f"**error**: {reply.get('error', 'recorder refused without a reason')}"
    path = reply.get("path", "?")
    if verb == "start":
        return f"recording to `{path}`"
    messages = reply.get("messages")
    total = sum(messages.values()) if isinstance(messages, dict) else messages
    extra = f": {total} messages" if total is not None else ""
    if isinstance(reply.get("bytes"), (int, float)):
        extra += f", {reply['bytes'] / 1e6:.1f} MB"
    return f"saved `{path}`{extra}"


def alerts_text(alerts: Sequence[Any]) -> str:
    """The newest alerts first, one line each: time, title, body (services/panel/alerts.py)."""
    if not alerts:
        return "no alerts"
    marks = {"error": "**error**", "warning": "warning", "info": "ok"}
    return "\n\n".join(f"{time.strftime('%H:%M:%S', time.localtime(a.at))} {marks.get(a.level, a.level)} "
                       f"**{a.title}**: {a.body}" for a in reversed(alerts))
