"""Where the glove's sensors sit on the 16 excitation x 16 reception lines of the readout module.

Thesis 4.8: five finger sensors and a 6x6 palm matrix with a 2x3 cutout (between thumb and index).
Our mapping (rows = excitation lines, cols = reception lines): the six reception lines run to
every sensor, each sensor has its own excitation lines, so only 16 x 6 crossings are read
(TX_MASK, RX_MASK: 423-byte frames, docs/protocols/tactile.md):

    rows 0-5   palm    6x6, without rows 4-5 x cols 3-5 (the cutout): 30 cells
    rows 6-7   thumb   2 across x 6 along the finger: 12 cells
    rows 8-9   index,  10-11 middle,  12-13 ring,  14-15 little: 12 cells each

Reception lines 6-15 are unused (masked out of the frames); the cutout crossings are not populated.
"""

from __future__ import annotations

import numpy as np

from shared.demo import TACTILE_REGIONS

ROWS = COLS = 16
CELL_AREA_M2 = 25e-6  # 5 mm x 5 mm electrodes


TX_MASK = 0xFFFF  # excitation lines the glove uses
RX_MASK = 0x003F  # reception lines the glove uses
FINGER_ROWS = {"thumb": 6, "index": 8, "middle": 10, "ring": 12, "little": 14}


def _layout() -> np.ndarray:
    region = np.full((ROWS, COLS), -1, int)
    region[0:6, 0:6] = TACTILE_REGIONS.index("palm")
    region[4:6, 3:6] = -1  # the 2x3 cutout
    for name, r in FINGER_ROWS.items():
        region[r:r + 2, 0:6] = TACTILE_REGIONS.index(name)
    return region


CELL_REGION = _layout()
CELL_MASK = (CELL_REGION >= 0).astype(np.uint8)
CELLS_PER_REGION = np.array([(CELL_REGION == i).sum() for i in range(len(TACTILE_REGIONS))])


def region_means(pressure: np.ndarray) -> np.ndarray:
    """Mean pressure per region (thumb, index, middle, ring, little, palm) from a 16x16 frame."""
    p = np.asarray(pressure, float).reshape(ROWS, COLS)
    sums = np.bincount(CELL_REGION[CELL_MASK == 1], weights=p[CELL_MASK == 1], minlength=len(TACTILE_REGIONS))
    return (sums / CELLS_PER_REGION).astype(np.float32)


def pressure_from_forces(region_forces: np.ndarray) -> np.ndarray:
    """Spread each region's normal force evenly over its cells: 16x16 pressure in kPa."""
    f = np.asarray(region_forces, float)
    per_cell = f / (CELLS_PER_REGION * CELL_AREA_M2) / 1e3
    out = np.zeros((ROWS, COLS))
    out[CELL_MASK == 1] = per_cell[CELL_REGION[CELL_MASK == 1]]
    return out


def region_pressure_kpa(region_forces: np.ndarray) -> np.ndarray:
    """Region mean pressure for region forces (what region_means of a perfect glove reports)."""
    return np.asarray(region_forces, float) / (CELLS_PER_REGION * CELL_AREA_M2) / 1e3
