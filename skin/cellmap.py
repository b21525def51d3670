"""The cell map of a design's placed sensors: one file that drives fabrication and software.

The file format, its reader and its checks are in shared/cellmap.py, which the glove service's
layout (services/glove/layout.py) and the tactile projection read without the skin tools; this
module builds the map from a design's placements (``xm skin`` writes ``<design>_cellmap.json``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from shared.cellmap import CellMap, CellMapError, check
from shared.cellmap import load as load_checked
from skin.errors import SkinError
from skin.layout import Placement

__all__ = ["CellMap", "cell_map", "load"]


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
    try:
        return check(CellMap(design.name, tuple(design.matrix), tuple(design.regions), sensors), design.name)
    except CellMapError as exc:
        raise SkinError("bad_cellmap", design.name, exc.problem) from None


def load(path: str | Path) -> CellMap:
    """Read a cell map; SkinError naming the file on a wrong format, naming the sensor on bad cells."""
    try:
        return load_checked(path)
    except CellMapError as exc:
        raise SkinError("bad_cellmap", Path(path).name, exc.problem) from None
