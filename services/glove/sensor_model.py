"""SIMULATED glove sensor: contact pressure -> complex cell measurement, for the world's readout module.

Each cell is a capacitor whose capacitance rises with pressure following the rational response
of thesis 4.5.6, dC/C0 = a*p / (1 + b*p) (stiffening dielectric), read out as a complex
admittance-like value G + j*w*C (arbitrary units, w*C0 ~ 1). On top: Gaussian noise, a slow
baseline drift and a little pressure/stretch crosstalk between neighbouring cells of the same
sensor (thesis 4.5.6). Unpopulated crossings read noise only.
"""

from __future__ import annotations

import numpy as np

from services.glove import layout as glove_layout
from services.glove.calibration import Calibration
from services.glove.layout import COLS, ROWS, Layout
from shared.protocols.tactile import TactileFrame

NOMINAL_A = 0.02  # 1/kPa: 2 % capacitance change per kPa at low pressure
NOMINAL_B = 0.01  # 1/kPa: saturation
NOISE = 0.0015
DRIFT = 0.002
CROSSTALK = 0.03


class GloveSensorModel:
    def __init__(self, seed: int = 0, layout: Layout | None = None) -> None:
        self.layout = layout or glove_layout.default()  # the glove's cells (None: the shipped cell map)
        rng = np.random.default_rng(seed)
        self.rng = rng
        self.c0 = rng.uniform(0.9, 1.1, (ROWS, COLS))  # per-cell baseline
        self.a = NOMINAL_A * rng.uniform(0.85, 1.15, (ROWS, COLS))
        self.b = NOMINAL_B * rng.uniform(0.85, 1.15, (ROWS, COLS))
        self.leak = rng.uniform(0.01, 0.03, (ROWS, COLS))
        self.drift_phase = rng.uniform(0, 2 * np.pi, (ROWS, COLS))

    def measure(self, pressure_kpa: np.ndarray, t: float) -> np.ndarray:
        p = np.maximum(pressure_kpa, 0.0)
        rel = self.a * p / (1.0 + self.b * p)
        # Stretching a cell couples into its row/column neighbours (a fraction of their change).
        rel = rel + CROSSTALK * self._neighbour_mean(rel)
        drift = DRIFT * np.sin(0.05 * t + self.drift_phase)
        cap = self.c0 * (1.0 + rel + drift) + self.rng.normal(0.0, NOISE, (ROWS, COLS))
        g = self.leak + self.rng.normal(0.0, NOISE, (ROWS, COLS))
        mask = self.layout.mask
        z = (g + 1j * cap) * mask + (1 - mask) * self.rng.normal(0.0, NOISE, (ROWS, COLS))
        return z.astype(np.complex64)

    def _neighbour_mean(self, x: np.ndarray) -> np.ndarray:
        """Mean of the 4-neighbours that belong to the same sensor (no coupling across sensors)."""
        region = self.layout.region
        total = np.zeros_like(x)
        count = np.zeros_like(x)
        for axis in (0, 1):
            for shift in (1, -1):
                same = (np.roll(region, shift, axis) == region) & (region >= 0)
                if axis == 0:
                    same[0 if shift == 1 else -1, :] = False  # no wrap-around
                else:
                    same[:, 0 if shift == 1 else -1] = False
                total += np.where(same, np.roll(x, shift, axis), 0.0)
                count += same
        return total / np.maximum(count, 1)

    def impedance(self, region_forces: np.ndarray, t: float) -> np.ndarray:
        return self.measure(self.layout.pressure_from_forces(region_forces), t)

    def frame(self, region_forces: np.ndarray, t: float, sequence: int) -> TactileFrame:
        """One protocol frame of the glove's lines (what the world's simulated module sends)."""
        return TactileFrame(sequence & 0xFFFFFFFF, int(round(t * 1e6)), self.impedance(region_forces, t), None,
                            self.layout.tx_mask, self.layout.rx_mask)

    def calibration(self) -> Calibration:
        """The calibration a perfect `xm glove calibrate` would find (no drift, no crosstalk)."""
        return Calibration(self.c0.copy(), self.a.copy(), self.b.copy(), self.layout.mask)


def nominal_calibration(seed: int = 0, layout: Layout | None = None) -> Calibration:
    """Factory calibration of the simulated gloves (the world seeds glove i with seed+i)."""
    return GloveSensorModel(seed, layout).calibration()
