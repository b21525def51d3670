"""Where the glove's sensors sit on the 16 excitation x 16 reception lines of the readout module.

Thesis 4.8: five finger sensors and a 6x6 palm matrix with a 2x3 cutout. Our mapping (rows =
excitation lines, cols = reception lines): palm rows 0-5 x cols 0-5 without rows 4-5 x cols 3-5
(30 cells); thumb rows 6-8 x cols 0-3, index rows 6-8 x cols 4-7, middle rows 9-11 x cols 0-3,
ring rows 9-11 x cols 4-7, little rows 12-14 x cols 0-3 (12 cells each). Other crossings are not
populated and are masked out.
"""

from __future__ import annotations

import numpy as np

from shared.demo import TACTILE_REGIONS

ROWS = COLS = 16
CELL_AREA_M2 = 25e-6  # 5 mm x 5 mm electrodes


def _layout() -> np.ndarray:
    region = np.full((ROWS, COLS), -1, int)
    region[0:6, 0:6] = TACTILE_REGIONS.index("palm")
    region[4:6, 3:6] = -1  # the cutout
    for name, (r, c) in {"thumb": (6, 0), "index": (6, 4), "middle": (9, 0), "ring": (9, 4),
                         "little": (12, 0)}.items():
        region[r:r + 3, c:c + 4] = TACTILE_REGIONS.index(name)
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
