"""The cell map: one file that drives fabrication and software.

It says, for every crossing of the readout matrix (rows = excitation lines, columns = reception
lines), which sensor region's cell is there (the glove's ``CELL_REGION`` in
services/glove/layout.py, regions in the order of ``shared.demo.TACTILE_REGIONS``), which lines
the readout enables (``TX_MASK``, ``RX_MASK``), and per sensor where each of its cells lies on the
base mesh (mm) with the surface normal there: what the tactile projection samples onto the hand.

JSON, ``"format": "crossmodal-skin-cellmap"``, ``"version": 1``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from skin.errors import SkinError
from skin.layout import Placement

FORMAT, VERSION = "crossmodal-skin-cellmap", 1


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
        Path(path).write_text(json.dumps(self.to_json(), indent=1))


def cell_map(design: Any, placements: list[Placement]) -> CellMap:
    """The cell map of a design's placed sensors (checked: no two cells on one crossing)."""
    sensors = []
    for p in placements:
        s = p.spec
        cells = [{"row": int(s.row0 + r), "col": int(s.col0 + c), "position": [round(float(x), 4) for x in pos],
                  "normal": [round(float(x), 5) for x in n]}
                 for (r, c), pos, n in zip(p.cells, p.cell_position, p.cell_normal, strict=True)]
        sensors.append({"name": s.name, "region": s.region, "row0": s.row0, "col0": s.col0, "rows": s.rows,
                        "cols": s.cols, "cutouts": [list(c) for c in s.cutouts], "cells": cells})
    return _checked(CellMap(design.name, tuple(design.matrix), tuple(design.regions), sensors), design.name)


def _checked(m: CellMap, name: str) -> CellMap:
    seen: dict[tuple[int, int], str] = {}
    for s in m.sensors:
        if s["region"] not in m.regions:
            raise SkinError("bad_cellmap", s["name"], f"region {s['region']!r} is not one of {list(m.regions)}")
        for c in s["cells"]:
            rc = (c["row"], c["col"])
            if not (0 <= rc[0] < m.matrix[0] and 0 <= rc[1] < m.matrix[1]):
                raise SkinError("bad_cellmap", s["name"], f"cell {rc} lies outside the {m.matrix[0]}x{m.matrix[1]} "
                                "readout matrix")
            if rc in seen:
                raise SkinError("bad_cellmap", s["name"], f"cell {rc} is also {seen[rc]}'s")
            seen[rc] = s["name"]
    return m


def load(path: str | Path) -> CellMap:
    """Read a cell map; SkinError naming the file on a wrong format, naming the sensor on bad cells."""
    name = Path(path).name
    try:
        d = json.loads(Path(path).read_text())
        if d.get("format") != FORMAT or d.get("version") != VERSION:
            raise SkinError("bad_cellmap", name, f"not a {FORMAT} version {VERSION} file")
        m = CellMap(d["design"], (int(d["matrix"]["rows"]), int(d["matrix"]["cols"])), tuple(d["regions"]),
                    d["sensors"])
        m = _checked(m, name)
        if m.region_matrix().tolist() != d["region"]:
            raise SkinError("bad_cellmap", name, "the region matrix disagrees with the sensors' cells")
        return m
    except (OSError, ValueError, KeyError, TypeError) as exc:
        if isinstance(exc, SkinError):
            raise
        raise SkinError("bad_cellmap", name, f"cannot read the cell map ({exc})") from exc
