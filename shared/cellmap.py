"""The cell map file: which sensor's cell sits at every crossing of a tactile readout matrix.

`xm skin` writes it (skin/cellmap.py); the glove service's layout (services/glove/layout.py) and,
through it, the tactile projection read it, so one file drives fabrication and software. The
glove's ships in models/skin/glove_cellmap.json.

JSON, ``"format": "crossmodal-skin-cellmap"``, ``"version": 1``:

- ``matrix``: ``rows`` (excitation lines), ``cols`` (reception lines), ``tx_mask`` and ``rx_mask``
  (the lines that carry a cell, as bit masks);
- ``regions``: region names; ``region``: the rows x cols matrix of region indices (-1: no cell);
- ``sensors``: per sensor its ``name``, ``region``, its block of the matrix (``row0``, ``col0``,
  ``rows``, ``cols``), the ``cutouts`` ([row, col, n_rows, n_cols] within the block) and its
  ``cells``: ``row``, ``col``, ``position`` on the base mesh (mm) and surface ``normal``.

The redundant fields (``region``, the masks) let a reader check the file: every one must agree
with the sensors' cells, and each sensor's cells must be its block less its cutouts.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

FORMAT, VERSION = "crossmodal-skin-cellmap", 1


class CellMapError(ValueError):
    """A cell map that cannot be used: the message names the file (or design) and the problem."""

    def __init__(self, source: str, problem: str) -> None:
        super().__init__(f"cell map {source}: {problem}")
        self.source, self.problem = source, problem


@dataclass
class CellMap:
    design: str
    matrix: tuple[int, int]
    regions: tuple[str, ...]
    sensors: list[dict[str, Any]]

    def region_matrix(self) -> np.ndarray:
        """(rows, cols) int: the region index of the cell at every crossing, -1 where none."""
        out = np.full(self.matrix, -1)
        for s in self.sensors:
            k = self.regions.index(s["region"])
            for c in s["cells"]:
                out[c["row"], c["col"]] = k
        return out

    def tx_mask(self) -> int:
        """Excitation lines (rows) that carry a cell, as a bit mask."""
        return int(sum(1 << int(r) for r in np.unique(np.nonzero(self.region_matrix() >= 0)[0])))

    def rx_mask(self) -> int:
        """Reception lines (columns) that carry a cell, as a bit mask."""
        return int(sum(1 << int(c) for c in np.unique(np.nonzero(self.region_matrix() >= 0)[1])))

    def positions(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every cell's (row, col) (C,2), position (C,3) and normal (C,3) on the base mesh (mm)."""
        cells = [c for s in self.sensors for c in s["cells"]]
        return (np.array([[c["row"], c["col"]] for c in cells]), np.array([c["position"] for c in cells]),
                np.array([c["normal"] for c in cells]))

    def to_json(self) -> dict[str, Any]:
        return {"format": FORMAT, "version": VERSION, "design": self.design, "units": "mm",
                "matrix": {"rows": self.matrix[0], "cols": self.matrix[1], "tx_mask": self.tx_mask(),
                           "rx_mask": self.rx_mask()},
                "regions": list(self.regions), "region": self.region_matrix().tolist(), "sensors": self.sensors}

    def save(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps(self.to_json(), indent=1) + "\n")


def _block(s: dict[str, Any]) -> set[tuple[int, int]]:
    """The crossings a sensor's block holds less its cutouts."""
    cut = {(s["row0"] + r + i, s["col0"] + c + j) for r, c, nr, nc in s["cutouts"] for i in range(nr)
           for j in range(nc)}
    return {(s["row0"] + i, s["col0"] + j) for i in range(s["rows"]) for j in range(s["cols"])} - cut


def check(m: CellMap, source: str) -> CellMap:
    """``m`` when its sensors are consistent: known regions, cells inside the matrix and inside the
    sensor's block less its cutouts, no crossing claimed twice; CellMapError naming the sensor."""
    rows, cols = m.matrix
    if rows <= 0 or cols <= 0:
        raise CellMapError(source, f"a {rows}x{cols} readout matrix")
    if len(set(m.regions)) != len(m.regions):
        raise CellMapError(source, f"region names repeat: {list(m.regions)}")
    seen: dict[tuple[int, int], str] = {}
    for s in m.sensors:
        name = s["name"]
        if s["region"] not in m.regions:
            raise CellMapError(source, f"{name}: region {s['region']!r} is not one of {list(m.regions)}")
        if not (0 <= s["row0"] and s["row0"] + s["rows"] <= rows and 0 <= s["col0"] and s["col0"] + s["cols"] <= cols):
            raise CellMapError(source, f"{name}: its {s['rows']}x{s['cols']} block at row {s['row0']}, column "
                               f"{s['col0']} runs outside the {rows}x{cols} readout matrix")
        cells = [(int(c["row"]), int(c["col"])) for c in s["cells"]]
        for rc in cells:
            if not (0 <= rc[0] < rows and 0 <= rc[1] < cols):
                raise CellMapError(source, f"{name}: cell {rc} lies outside the {rows}x{cols} readout matrix")
            if rc in seen:
                raise CellMapError(source, f"{name}: cell {rc} is also {seen[rc]}'s")
            seen[rc] = name
        if set(cells) != _block(s) or len(cells) != len(set(cells)):
            raise CellMapError(source, f"{name}: its cells are not its {s['rows']}x{s['cols']} block at row "
                               f"{s['row0']}, column {s['col0']} less its cutouts {s['cutouts']}")
    return m


def from_json(d: dict[str, Any], source: str) -> CellMap:
    """The cell map of a parsed file, checked (also its region matrix and masks against the cells)."""
    if not isinstance(d, dict) or d.get("format") != FORMAT or d.get("version") != VERSION:
        raise CellMapError(source, f"not a {FORMAT} version {VERSION} file")
    try:
        mat = d["matrix"]
        m = CellMap(str(d["design"]), (int(mat["rows"]), int(mat["cols"])), tuple(str(r) for r in d["regions"]),
                    list(d["sensors"]))
        check(m, source)
        region = np.asarray(d["region"])
        masks = (int(mat["tx_mask"]), int(mat["rx_mask"]))
    except (KeyError, TypeError, ValueError) as exc:
        if isinstance(exc, CellMapError):
            raise
        raise CellMapError(source, f"a field is missing or of the wrong type ({exc!r})") from None
    if region.shape != m.matrix:
        raise CellMapError(source, f"the region matrix is {region.shape}, the readout matrix {m.matrix}")
    if not np.array_equal(region, m.region_matrix()):
        bad = tuple(int(x) for x in np.argwhere(region != m.region_matrix())[0])
        raise CellMapError(source, f"the region matrix disagrees with the sensors' cells (first at crossing {bad})")
    if masks != (m.tx_mask(), m.rx_mask()):
        raise CellMapError(source, f"tx_mask/rx_mask {masks[0]:#x}/{masks[1]:#x} disagree with the lines the cells "
                           f"occupy ({m.tx_mask():#x}/{m.rx_mask():#x})")
    return m


def load(path: str | Path) -> CellMap:
    """Read and check a cell map; CellMapError naming the file and the problem."""
    try:
        d = json.loads(Path(path).read_text())
    except OSError as exc:
        raise CellMapError(str(path), f"cannot read it ({exc.strerror or exc})") from None
    except ValueError as exc:
        raise CellMapError(str(path), f"not JSON ({exc})") from None
    return from_json(d, str(path))
