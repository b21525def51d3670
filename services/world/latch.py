"""The assembly's connector pressed until it latches (thesis 7.6.8, "pressing the connector"): the
connector snaps home at ``LATCH_FORCE_N``; force, not position, decides.

The teacher's index finger comes down onto the mated connector and pushes through the snap (its
peak force drawn per demonstration in ``PEAK_FORCE_N``); the finger's pad and the connector's
travel give under the press by force / ``FINGER_N_PER_M`` (under a millimetre at the latch force),
so the keypoints show the press only as that sub-millimetre dip. The glove (on the pressing hand)
reads the force on the index region.

Success (``outcome``): the module's connector on the board's (within SEAT_GAP_M) while a finger
over it presses with at least LATCH_FORCE_N and never more than DAMAGE_FORCE_N, and the board
lifted with the module afterwards.
"""

from __future__ import annotations

import numpy as np

from services.world.tracks import Track

LATCH_FORCE_N = 5.0  # the snap-fit's engagement force
DAMAGE_FORCE_N = 12.0  # above this the flex cable's connector breaks
PEAK_FORCE_N = (5.6, 7.0)  # the teacher pushes through the snap
FINGER_N_PER_M = 6000.0  # fingertip pad plus connector travel: 6 N dips the tip 1 mm
TIP_CONTACT_Z = 0.0055  # index tip above the board's connector keypoint when just touching
OVER_CONNECTOR_M = 0.006  # a fingertip this close (horizontally) presses on the connector
CLOSE_M = 0.005  # force control: a predicted press moves the tip down this far to the connector
SEAT_GAP_M = 0.003  # connectors aligned (services/world/sim.SEAT_GAP_M)
LIFTED_M = 0.02


def sample_force(rng: np.random.Generator) -> float:
    return float(rng.uniform(*PEAK_FORCE_N))


class PressPath:
    """The pressing index tip: the assembly's approach and retreat, lowered by the press's dip."""

    def __init__(self, moves: Track, force: Track) -> None:
        self.moves, self.force = moves, force

    def __call__(self, t: float) -> np.ndarray:
        p = self.moves(t).copy()
        p[2] -= float(self.force(t)[0]) / FINGER_N_PER_M
        return p


def press_tracks(T, board_conn: np.ndarray, approach: np.ndarray, retreat: np.ndarray, start: np.ndarray,
                 peak_n: float) -> tuple[PressPath, Track, tuple[float, float]]:
    """Tip path, force track (N) and press window: touch at 5.6, ramp through the snap to ``peak_n``
    at 6.0, let go by 6.3."""
    touch = board_conn + [0, 0, TIP_CONTACT_Z]
    moves = (Track().add(0, start).hold(T(0.5)).add(T(2.2), approach).hold(T(5.0))
             .add(T(5.4), board_conn + [0, 0, 0.012]).add(T(5.6), touch).hold(T(6.3))
             .add(T(6.6), retreat).add(T(8.0), start))
    force = Track().add(0, 0.0).hold(T(5.6)).add(T(6.0), peak_n).add(T(6.3), 0.0).hold(T(8.0))
    return PressPath(moves, force), force, (T(5.6), T(6.3))


# --- the success test ------------------------------------------------------------------------
def _press_hand(hands: np.ndarray, conn: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Index tips (T,2,3) and, per step, the hand whose index tip is closest to the board's connector."""
    tips = hands[:, :, 8]
    near = np.argmin(np.linalg.norm(tips[:, :, :2] - conn[:, None, :2], axis=-1), axis=1)
    return tips, near


def press_from_tactile(hands: np.ndarray, objects: np.ndarray, names: list[str], tactile: np.ndarray,
                       kpa_per_n: float, index_region: int, contact_m: float = CLOSE_M) -> np.ndarray:
    """(T,) N on the connector from the (predicted or measured) index pressure of the hand whose index
    tip is over it and at most ``contact_m`` above its touching height (force control closes that
    gap, as on wiping); zero elsewhere."""
    conn = objects[:, names.index("board/connector")]
    tips, near = _press_hand(hands, conn)
    steps = np.arange(len(hands))
    tip = tips[steps, near]
    over = np.linalg.norm(tip[:, :2] - conn[:, :2], axis=-1) <= OVER_CONNECTOR_M
    close = tip[:, 2] - (conn[:, 2] + TIP_CONTACT_Z) <= contact_m
    return np.where(over & close, tactile[steps, near, index_region] / kpa_per_n, 0.0)


def press_from_positions(hands: np.ndarray, objects: np.ndarray, names: list[str]) -> np.ndarray:
    """(T,) N a position-controlled finger following these keypoints would press with: its dip
    below the touching height times the pad's and connector's stiffness."""
    conn = objects[:, names.index("board/connector")]
    tips, near = _press_hand(hands, conn)
    steps = np.arange(len(hands))
    tip = tips[steps, near]
    over = np.linalg.norm(tip[:, :2] - conn[:, :2], axis=-1) <= OVER_CONNECTOR_M
    dip = conn[:, 2] + TIP_CONTACT_Z - tip[:, 2]
    return np.where(over, FINGER_N_PER_M * np.clip(dip, 0.0, None), 0.0)


def outcome(objects: np.ndarray, names: list[str], force_n: np.ndarray) -> dict:
    """The world's success test over a trajectory: objects (T,K,3), force_n (T,) N on the connector."""
    gap = np.linalg.norm(objects[:, names.index("camera/connector")] - objects[:, names.index("board/connector")],
                         axis=-1)
    aligned = gap < SEAT_GAP_M
    latched_at = np.flatnonzero(aligned & (force_n >= LATCH_FORCE_N))
    peak = float(force_n.max(initial=0.0))
    board_z = min(objects[-1, names.index(f"board/c{i}"), 2] for i in range(4))
    latched = latched_at.size > 0 and peak <= DAMAGE_FORCE_N
    return {"latched": bool(latched), "peak_force_n": peak, "min_gap_mm": float(gap.min() * 1e3),
            "lifted": bool(board_z > LIFTED_M), "success": bool(latched and board_z > LIFTED_M)}
