"""Bottle (thesis 7.6.3): the cap is grasped, twisted off under the thread's load in repeated
turns (grip, turn, let go, turn back) and lifted, while the other hand holds the bottle.

The thread needs a grip: the cap turns with the fingers only while they squeeze it with at least
``SLIP_GRIP_N`` per finger, otherwise they slip over it. It comes free after ``UNSCREW_TURNS``
turns, rising ``PITCH_M`` per turn. The squeeze shows in the keypoints only as the fingers'
closing: the fingertips' pads give by force / ``GRIP_N_PER_M`` (2.5 mm at 5 N) inside the cap's
diameter. The glove reads the grip on thumb and index.

Success (``outcome``): the cap turned by at least ``UNSCREW_TURNS`` at steps where the grip held
it (>= SLIP_GRIP_N), and it ends 3 cm above the bottle's neck.
"""

from __future__ import annotations

import numpy as np

from services.world.tracks import Track

BOTTLE_R, BOTTLE_H = 0.030, 0.120
CAP_R, CAP_H = 0.016, 0.016
SLIP_GRIP_N = 3.0  # per finger: less and the fingers slip on the cap under the thread's torque
GRIP_N = (4.5, 6.0)  # the teacher's grip while turning, drawn per demonstration
HOLD_N = 3.0  # the other hand's palm on the bottle
LIGHT_GRIP_N = 1.0  # carrying the loose cap
GRIP_N_PER_M = 2000.0
UNSCREW_TURNS = 1.0
PITCH_M = 0.003  # thread rise per turn
TWISTS = 4  # turns of TWIST_RAD each
TWIST_RAD = 1.75  # 100 degrees: four of them unscrew the cap with a margin
LIFTED_M = 0.03

OBJECT_POINTS = {
    "bottle": {"base": (0.0, 0.0, 0.0), "neck": (0.0, 0.0, BOTTLE_H), "side": (BOTTLE_R, 0.0, 0.06),
               "side2": (0.0, BOTTLE_R, 0.06)},
    "cap": {"top": (0.0, 0.0, CAP_H), "mark": (CAP_R, 0.0, CAP_H / 2), "mark2": (0.0, CAP_R, CAP_H / 2)},
}
GEOMS = {
    "bottle": [("cylinder", (BOTTLE_R, BOTTLE_H / 2, 0.0), (0.0, 0.0, BOTTLE_H / 2), (0.4, 0.7, 0.9, 0.8), 0.3)],
    "cap": [("cylinder", (CAP_R, CAP_H / 2, 0.0), (0.0, 0.0, CAP_H / 2), (0.9, 0.2, 0.2, 1), 0.005),
            ("box", (0.003, 0.002, 0.002), (CAP_R, 0.0, CAP_H / 2), (0.1, 0.1, 0.1, 1), 0.0005)],
}


def sample_layout(rng: np.random.Generator) -> dict:
    return {"bottle": [rng.uniform(-0.06, 0.10), rng.uniform(-0.08, 0.08), rng.uniform(-np.pi, np.pi)],
            "grip_n": float(rng.uniform(*GRIP_N))}


def build(teacher, rng: np.random.Generator, T, jitter, start_g: np.ndarray, start_p: np.ndarray,
          pinch_square: float) -> None:
    """Sets the bottle script's tracks and timing on ``teacher`` (services/world/teacher.Teacher)."""
    bx, by, byaw = teacher.layout["bottle"]
    grip_n = teacher.layout["grip_n"]
    base = np.array([bx, by, 0.0])
    cap_grip = base + [0, 0, BOTTLE_H + CAP_H / 2]
    hold = base + [-BOTTLE_R - 0.004, 0.0, 0.07]  # the other hand's index beside the bottle
    squeeze = 2 * CAP_R - grip_n / GRIP_N_PER_M  # thumb-index distance while turning
    yaw0 = float(rng.uniform(-0.3, 0.3)) + pinch_square
    pin = (Track().add(0, start_g).hold(T(0.5)).add(T(1.8), cap_grip + [0, 0, 0.05] + jitter(0.003))
           .add(T(2.3), cap_grip))
    yaw = Track().add(0, 0.0).hold(T(0.5)).add(T(2.0), yaw0)
    aperture = Track().add(0, 0.05).hold(T(2.0)).add(T(2.3), 2 * CAP_R + 0.008)
    grip = Track().add(0, 0.0).hold(T(2.3))
    twists, t = [], T(2.3)
    for k in range(TWISTS):
        close, turned, opened, back = t + T(0.25), t + T(0.95), t + T(1.2), t + T(1.6)
        rise = PITCH_M * TWIST_RAD * (k + 1) / (2 * np.pi)
        aperture.add(close, squeeze).hold(turned).add(opened, 2 * CAP_R + 0.008)
        grip.add(close, grip_n).hold(turned).add(opened, 0.0)
        yaw.hold(close).add(turned, yaw0 + TWIST_RAD).hold(opened)
        pin.add(close, pin.values[-1]).add(turned, cap_grip + [0, 0, rise]).hold(opened)
        if k < TWISTS - 1:
            yaw.add(back, yaw0)
            aperture.hold(back)
            grip.hold(back)
            pin.hold(back)
        twists.append((close, turned))
        t = back if k < TWISTS - 1 else opened
    # the loose cap: a light grip and up
    aperture.add(t + T(0.25), 2 * CAP_R - LIGHT_GRIP_N / GRIP_N_PER_M).hold(T(11.0))
    grip.add(t + T(0.25), LIGHT_GRIP_N).hold(T(11.0))
    yaw.hold(T(11.0))
    pin.hold(t + T(0.3)).add(t + T(1.2), pin.values[-1] + [0, 0, 0.08]).hold(T(11.0))
    teacher.pinch, teacher.pinch_yaw, teacher.aperture, teacher.grip = pin, yaw, aperture, grip
    teacher.tip = Track().add(0, start_p).hold(T(0.5)).add(T(1.8), hold + [-0.03, 0, 0.02]).add(T(2.2), hold) \
        .hold(t + T(0.3)).add(t + T(1.2), start_p).hold(T(11.0))
    teacher.hold_window = (T(2.2), t + T(0.3))
    teacher.press_yaw = Track().add(0, 0.0).hold(T(11.0))
    teacher.opposition = Track().add(0, 0.3).add(T(1.8), 1.0).hold(T(11.0))
    teacher.twists = twists
    teacher.free_time = t + T(0.3)  # the cap is loose and carried from here
    teacher.phases = [(0.0, "approach"), (T(2.3), "twist"), (t, "lift"), (t + T(1.4), "done")]
    teacher.grasp_window = (T(2.3), np.inf)
    teacher.press_window = (np.inf, np.inf)
    teacher.insert_time = np.inf
    teacher.base0, teacher.byaw, teacher.cap_yaw0 = base, byaw, float(rng.uniform(-np.pi, np.pi))
    teacher.duration = T(11.0)


def cap_turn(teacher, t: float) -> float:
    """How far the cap has turned by time t: with the hand, during each gripped twist."""
    turn = 0.0
    for start, end in teacher.twists:
        if t > start:
            turn += float(teacher.pinch_yaw(min(t, end))[0] - teacher.pinch_yaw(start)[0])
    return turn


def objects(teacher, t: float, pinch_now: np.ndarray) -> dict[str, tuple[np.ndarray, float]]:
    turn = cap_turn(teacher, t)
    if t >= teacher.free_time:
        cap = pinch_now - [0, 0, CAP_H / 2]
    else:
        cap = teacher.base0 + [0, 0, BOTTLE_H + PITCH_M * turn / (2 * np.pi)]
    return {"bottle": (teacher.base0.copy(), teacher.byaw), "cap": (cap, teacher.cap_yaw0 + turn)}


def forces(teacher, t: float, regions: tuple[str, ...], grasp: int, other: int) -> np.ndarray:
    out = np.zeros((2, len(regions)))
    g = float(teacher.grip(t)[0])
    out[grasp, regions.index("thumb")] = out[grasp, regions.index("index")] = g
    h0, h1 = teacher.hold_window
    if h0 - 0.2 <= t < h1 + 0.2:
        out[other, regions.index("palm")] = HOLD_N * float(np.clip(min((t - h0 + 0.2) / 0.2, (h1 + 0.2 - t) / 0.2),
                                                                    0.0, 1.0))
    return out


# --- the success test ------------------------------------------------------------------------
def _grip_hand(hands: np.ndarray, cap: np.ndarray) -> np.ndarray:
    """Per step, the hand whose pinch is closest to the cap's top."""
    pinch = 0.5 * (hands[:, :, 4] + hands[:, :, 8])
    return np.argmin(np.linalg.norm(pinch - cap[:, None], axis=-1), axis=1)


def grip_from_tactile(hands: np.ndarray, objects: np.ndarray, names: list[str], tactile: np.ndarray,
                      kpa_per_n: float, regions: tuple[str, ...]) -> np.ndarray:
    """(T,) N per finger on the cap: the smaller of thumb and index of the hand at the cap."""
    near = _grip_hand(hands, objects[:, names.index("cap/top")])
    steps = np.arange(len(hands))
    t, i = tactile[steps, near, regions.index("thumb")], tactile[steps, near, regions.index("index")]
    return np.minimum(t, i) / kpa_per_n


def grip_from_positions(hands: np.ndarray, objects: np.ndarray, names: list[str]) -> np.ndarray:
    """(T,) N per finger a position-controlled gripper closing to these fingertips would squeeze the
    cap with: how far inside the cap's diameter they close, times the pads' stiffness; zero where
    the pinch is not at the cap."""
    cap = objects[:, names.index("cap/top")]
    near = _grip_hand(hands, cap)
    steps = np.arange(len(hands))
    thumb, index = hands[steps, near, 4], hands[steps, near, 8]
    at_cap = np.linalg.norm(0.5 * (thumb + index) - (cap - [0, 0, CAP_H / 2]), axis=-1) < CAP_R
    squeeze = 2 * CAP_R - np.linalg.norm(thumb - index, axis=-1)
    return np.where(at_cap, GRIP_N_PER_M * np.clip(squeeze, 0.0, None), 0.0)


def cap_yaw(objects: np.ndarray, names: list[str]) -> np.ndarray:
    """(T,) the cap's heading relative to the bottle's, unwrapped."""
    def heading(a: str, b: str) -> np.ndarray:
        d = objects[:, names.index(a)] - objects[:, names.index(b)]
        return np.arctan2(d[:, 1], d[:, 0])
    rel = heading("cap/mark", "cap/top") - heading("bottle/side", "bottle/base")
    return np.unwrap(rel)


def outcome(objects: np.ndarray, names: list[str], grip_n: np.ndarray) -> dict:
    yaw = cap_yaw(objects, names)
    step = np.diff(yaw)
    held = grip_n[1:] >= SLIP_GRIP_N
    turned = float(np.clip(step[held], 0.0, None).sum() / (2 * np.pi))  # unscrewing turns while held
    rise = float(objects[-1, names.index("cap/top"), 2] - objects[-1, names.index("bottle/neck"), 2] - CAP_H)
    return {"turns": turned, "cap_rise_mm": rise * 1e3, "peak_grip_n": float(grip_n.max(initial=0.0)),
            "success": bool(turned >= UNSCREW_TURNS and rise >= LIFTED_M)}
