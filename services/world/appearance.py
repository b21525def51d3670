"""What the simulated cameras see of the teacher: hands drawn as capsules between the 21 keypoints
(skin, or the glove's fabric on the gloved hand), a forearm in a sleeve, and the session's lighting.

Pure: keypoints and seeds in, capsule lists and light parameters out; services/world/render.py
puts them into MuJoCo's scene.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# MANO/OpenPose order: 0 wrist, 1-4 thumb (CMC, MCP, IP, tip), 5-8 index, 9-12 middle, 13-16 ring,
# 17-20 little (MCP, PIP, DIP, tip).
FINGER_BASES = (1, 5, 9, 13, 17)
PALM_BONES = ((0, 1), (0, 5), (0, 9), (0, 13), (0, 17), (1, 5), (5, 9), (9, 13), (13, 17), (1, 9))
PALM_RADIUS = 0.013
FINGER_RADII = {1: 0.010, 5: 0.0085, 9: 0.0088, 13: 0.0083, 17: 0.0072}  # proximal phalanx; tapers distally
TAPER = 0.85  # each phalanx is this much thinner than the one before
FOREARM_LENGTH = 0.22
FOREARM_RADIUS = 0.025
FOREARM_RISE = 0.5  # the forearm's slope is this fraction of the hand's: teachers reach in from the side
# Phalanx shading: proximal, middle, distal relative to the hand's base colour; neighbouring segments
# of one finger differ so a detector (and a reader) can tell them apart.
PHALANX_SHADE = (0.8, 1.0, 1.15)

SKIN_TONES = np.array([[0.96, 0.80, 0.69], [0.91, 0.71, 0.58], [0.80, 0.60, 0.45], [0.63, 0.45, 0.32],
                       [0.45, 0.31, 0.22]])
GLOVE_COLOR = np.array([0.18, 0.22, 0.30])  # the tactile glove's dark blue-grey fabric
SLEEVES = np.array([[0.2, 0.3, 0.5], [0.55, 0.55, 0.55], [0.15, 0.15, 0.15], [0.6, 0.2, 0.2], [0.3, 0.45, 0.3]])


@dataclass(frozen=True)
class Capsule:
    a: np.ndarray  # (3,) end points, world frame
    b: np.ndarray
    radius: float
    rgba: tuple[float, float, float, float]


@dataclass(frozen=True)
class Box:
    pos: np.ndarray  # (3,) centre, world frame
    half: np.ndarray  # (3,) half extents
    rgba: tuple[float, float, float, float]


# The room around the table as the cameras see it: the floor 75 cm below the table top and the
# rig's four aluminium posts (80 cm cube, thesis 5.4). The physics model has neither.
FLOOR_DEPTH = 0.75
ROOM = (Box(np.array([0.0, 0.0, -FLOOR_DEPTH - 0.01]), np.array([4.0, 4.0, 0.01]), (0.22, 0.21, 0.2, 1.0)),
        *(Box(np.array([x, y, 0.4]), np.array([0.012, 0.012, 0.4]), (0.62, 0.63, 0.65, 1.0))
          for x in (-0.4, 0.4) for y in (-0.4, 0.4)))


@dataclass(frozen=True)
class Look:
    """The teacher's appearance for one session: skin tone and sleeve colour."""
    skin: np.ndarray  # (3,) rgb in [0, 1]
    sleeve: np.ndarray


@dataclass(frozen=True)
class Lighting:
    """One session's light: a key light (direction, colour) plus ambient and headlight levels."""
    pos: np.ndarray  # (3,)
    dir: np.ndarray  # (3,) unit, pointing down into the cell
    diffuse: np.ndarray  # (3,)
    ambient: np.ndarray  # (3,)
    headlight: float  # diffuse of the light at the viewer (fills shadows)


def session_rng(seed: int, demo: int, stream: int) -> np.random.Generator:
    """One generator per (seed, demo, what it draws): the look and the lighting vary independently."""
    return np.random.default_rng([int(seed), int(demo), int(stream), 0x5CE])


def session_look(seed: int, demo: int) -> Look:
    rng = session_rng(seed, demo, 1)
    skin = SKIN_TONES[rng.integers(len(SKIN_TONES))] * rng.uniform(0.94, 1.04)
    sleeve = SLEEVES[rng.integers(len(SLEEVES))]
    return Look(np.clip(skin, 0, 1), sleeve)


def session_lighting(seed: int, demo: int) -> Lighting:
    """A key light somewhere above the cell, warm to cool white, brighter or dimmer per session."""
    rng = session_rng(seed, demo, 2)
    azimuth, tilt = rng.uniform(0, 2 * np.pi), rng.uniform(0.0, 0.6)
    direction = np.array([np.sin(tilt) * np.cos(azimuth), np.sin(tilt) * np.sin(azimuth), -np.cos(tilt)])
    level = rng.uniform(0.45, 0.8)
    warmth = rng.uniform(-0.08, 0.08)  # + warm, - cool
    diffuse = level * np.array([1 + warmth, 1.0, 1 - warmth])
    return Lighting(pos=-1.5 * direction, dir=direction, diffuse=np.clip(diffuse, 0, 1),
                    ambient=np.full(3, rng.uniform(0.1, 0.22)), headlight=float(rng.uniform(0.05, 0.2)))


def _rgba(rgb: np.ndarray, shade: float = 1.0) -> tuple[float, float, float, float]:
    r, g, b = np.clip(np.asarray(rgb) * shade, 0, 1)
    return float(r), float(g), float(b), 1.0


def hand_capsules(keypoints: np.ndarray, base_rgb: np.ndarray, sleeve_rgb: np.ndarray | None = None) -> list[Capsule]:
    """Capsules that draw one hand from its (21,3) keypoints: palm, three phalanges per finger in
    alternating shades, and a forearm (sleeve) behind the wrist.

    A hand parked away from the cell (all keypoints below the table) draws nothing."""
    k = np.asarray(keypoints, float)
    if k.shape != (21, 3) or not np.all(np.isfinite(k)) or np.all(k[:, 2] < -0.5):
        return []
    out = [Capsule(k[a], k[b], PALM_RADIUS if a == 0 else PALM_RADIUS * 0.8, _rgba(base_rgb, 0.95))
           for a, b in PALM_BONES]
    for base in FINGER_BASES:
        radius = FINGER_RADII[base]
        for s in range(3):
            a, b = base + s, base + s + 1
            out.append(Capsule(k[a], k[b], radius, _rgba(base_rgb, PHALANX_SHADE[s])))
            radius *= TAPER
    if sleeve_rgb is not None:
        back = k[0] - k[9]  # forearm continues the line from the middle finger's base through the wrist
        back[2] *= FOREARM_RISE
        norm = np.linalg.norm(back)
        if norm > 1e-6:
            elbow = k[0] + back / norm * FOREARM_LENGTH
            out.append(Capsule(k[0] + back / norm * 0.03, elbow, FOREARM_RADIUS, _rgba(sleeve_rgb)))
    return out


def teacher_capsules(hands: np.ndarray, names: tuple[str, ...], glove_hand: str, look: Look) -> list[Capsule]:
    """Both hands: the gloved one in the glove's fabric, the other in the session's skin tone."""
    out: list[Capsule] = []
    for name, keypoints in zip(names, np.asarray(hands, float), strict=True):
        out += hand_capsules(keypoints, GLOVE_COLOR if name == glove_hand else look.skin, look.sleeve)
    return out
