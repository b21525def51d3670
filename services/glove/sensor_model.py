"""SIMULATED glove sensor: contact pressure -> complex cell measurement, for the world's readout module.

Each cell is a capacitor whose capacitance rises with pressure following the rational response
of thesis 4.5.6, dC/C0 = a*p / (1 + b*p) (stiffening dielectric), read out as a complex
admittance-like value G + j*w*C (arbitrary units, w*C0 ~ 1). On top: Gaussian noise, a slow
baseline drift and a little crosstalk from stretching neighbours.
"""

from __future__ import annotations

import numpy as np

from services.glove.calibration import Calibration
from services.glove.layout import CELL_MASK, COLS, ROWS, pressure_from_forces

NOMINAL_A = 0.02  # 1/kPa: 2 % capacitance change per kPa at low pressure
NOMINAL_B = 0.01  # 1/kPa: saturation
NOISE = 0.0015
DRIFT = 0.002
CROSSTALK = 0.03


class GloveSensorModel:
    def __init__(self, seed: int = 0) -> None:
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
        neighbours = (np.roll(rel, 1, 0) + np.roll(rel, -1, 0) + np.roll(rel, 1, 1) + np.roll(rel, -1, 1)) / 4
        rel = rel + CROSSTALK * neighbours
        drift = DRIFT * np.sin(0.05 * t + self.drift_phase)
        cap = self.c0 * (1.0 + rel + drift) + self.rng.normal(0.0, NOISE, (ROWS, COLS))
        g = self.leak + self.rng.normal(0.0, NOISE, (ROWS, COLS))
        z = (g + 1j * cap) * CELL_MASK + (1 - CELL_MASK) * self.rng.normal(0.0, NOISE, (ROWS, COLS))
        return z.astype(np.complex64)

    def impedance(self, region_forces: np.ndarray, t: float) -> np.ndarray:
        return self.measure(pressure_from_forces(region_forces), t)

    def calibration(self) -> Calibration:
        """The calibration a perfect `xm glove calibrate` would find (no drift, no crosstalk)."""
        return Calibration(self.c0.copy(), self.a.copy(), self.b.copy())


def nominal_calibration(seed: int = 0) -> Calibration:
    """Factory calibration of the simulated gloves (the world seeds glove i with seed+i)."""
    return GloveSensorModel(seed).calibration()
